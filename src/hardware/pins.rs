//! The board's pins, put in their modes at start-up for the board profile
//! ([`super::profile`]): the DAC outputs and the sensor in analog mode, the host link's TX/RX
//! in AF7, the trigger I/O, and (driver board, `dual-stage`) the coarse axis's pins.

use stm32f4xx_hal::gpio::GpioExt;
use stm32f4xx_hal::pac;
use stm32f4xx_hal::rcc::Rcc;

use super::trigger_pins::TriggerPins;

/// The coarse axis's pins on the driver board (feature `dual-stage`): STEP on PA8 (TIM1 CH1,
/// AF1), the encoders on PC6/PC7 (TIM8, AF3) and PB6/PB7 (TIM4, AF2) are put in their
/// alternate functions; DIR and the switches are handed on.
#[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
pub struct CoarsePins {
    /// DIR (PB0, push-pull).
    pub dir: stm32f4xx_hal::gpio::Pin<'B', 0, stm32f4xx_hal::gpio::Output>,
    /// The limit and home switches (PC0–PC2).
    pub switches: super::coarse_stage::BoardSwitches,
}

/// The pins the application keeps, configured.
pub struct Pins {
    /// The trigger I/O.
    pub triggers: TriggerPins,
    /// The coarse axis's (driver board, `dual-stage`).
    #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
    pub coarse: CoarsePins,
}

/// Puts every pin the image uses in its mode: the DAC outputs and the sensor in analog mode,
/// the link's TX/RX in AF7, the trigger outputs low and the input pulled down (and, with the
/// coarse axis, its pins). The analog and alternate-function pins keep their mode when their
/// handles are dropped here.
#[cfg(not(feature = "feather"))]
pub fn configure(gpioa: pac::GPIOA, gpiob: pac::GPIOB, gpioc: pac::GPIOC, rcc: &mut Rcc) -> Pins {
    let gpioa = gpioa.split(rcc);
    let _dac_left = gpioa.pa4.into_analog();
    let _dac_right = gpioa.pa5.into_analog();
    let _sensor = gpioa.pa0.into_analog();
    let _tx_pin = gpioa.pa9.into_alternate::<7>();
    let _rx_pin = gpioa.pa10.into_alternate::<7>();
    let triggers = TriggerPins::new(
        gpioa.pa1.into_push_pull_output(),
        gpioa.pa2.into_push_pull_output(),
        gpioa.pa3.into_push_pull_output(),
        gpioa.pa6.into_pull_down_input(),
        gpioa.pa7.into_push_pull_output(),
    );
    #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
    let coarse = {
        let gpiob = gpiob.split(rcc);
        let gpioc = gpioc.split(rcc);
        let _step_pin = gpioa.pa8.into_alternate::<1>();
        let _linear_a = gpiob.pb6.into_alternate::<2>();
        let _linear_b = gpiob.pb7.into_alternate::<2>();
        let _motor_a = gpioc.pc6.into_alternate::<3>();
        let _motor_b = gpioc.pc7.into_alternate::<3>();
        CoarsePins {
            dir: gpiob.pb0.into_push_pull_output(),
            switches: super::coarse_stage::BoardSwitches::new(
                gpioc.pc0.into_pull_up_input(),
                gpioc.pc1.into_pull_up_input(),
                gpioc.pc2.into_pull_up_input(),
            ),
        }
    };
    #[cfg(not(all(feature = "dual-stage", not(feature = "emulator"))))]
    let _ = (gpiob, gpioc);
    Pins {
        triggers,
        #[cfg(all(feature = "dual-stage", not(feature = "emulator")))]
        coarse,
    }
}

/// Puts every pin the image uses in its mode (see the driver board's), on the Feather's
/// header: A0/A1 (PA4/PA5) DAC, A2 (PA6) sensor, TX/RX (PB10/PB11) USART3 in AF7, D13/D12/D11
/// (PC1–PC3) and D5 (PC7) outputs, D6 (PC6) input.
#[cfg(feature = "feather")]
pub fn configure(gpioa: pac::GPIOA, gpiob: pac::GPIOB, gpioc: pac::GPIOC, rcc: &mut Rcc) -> Pins {
    let gpioa = gpioa.split(rcc);
    let gpiob = gpiob.split(rcc);
    let gpioc = gpioc.split(rcc);
    let _dac_left = gpioa.pa4.into_analog();
    let _dac_right = gpioa.pa5.into_analog();
    let _sensor = gpioa.pa6.into_analog();
    let _tx_pin = gpiob.pb10.into_alternate::<7>();
    let _rx_pin = gpiob.pb11.into_alternate::<7>();
    let triggers = TriggerPins::new(
        gpioc.pc1.into_push_pull_output(),
        gpioc.pc2.into_push_pull_output(),
        gpioc.pc3.into_push_pull_output(),
        gpioc.pc6.into_pull_down_input(),
        gpioc.pc7.into_push_pull_output(),
    );
    Pins { triggers }
}
