//! Board support for the STM32F405 boards (firmware build only): the twinstack driver board,
//! and — with the `feather` feature — the Adafruit Feather STM32F405 Express, whose pins,
//! crystal and host-link USART are in [`profile`]. The table below is the driver board's.
//!
//! Each module wraps one peripheral; [`setup`] brings the board up from them and holds every
//! task's body, so the RTIC shells (`src/bin/twinstack-*.rs`) only bind interrupts. The
//! control algorithm never sees a register, only the [`crate::board`] traits that
//! [`dac::InternalDac`] and [`adc::SensorInput`] implement.
//!
//! | signal | pin | peripheral |
//! |--------|-----|------------|
//! | left stack drive `u_l` | PA4 | DAC channel 1 |
//! | right stack drive `u_r` | PA5 | DAC channel 2 |
//! | position sensor | PA0 | ADC1 channel 0, triggered by TIM2 TRGO |
//! | analog setpoint input (0–3.3 V) | PC3 | ADC2 channel 13, triggered by TIM2 TRGO ([`setpoint_adc`]) |
//! | host link TX / RX | PA9 / PA10 | USART1 (AF7), RX by DMA2 stream 2 channel 4 |
//! | SWD | PA13 / PA14 | debug probe |
//! | coarse stage STEP / DIR | PA8 / PB0 | TIM1 CH1 (AF1) / GPIO ([`coarse_stage`]) |
//! | motor encoder A / B | PC6 / PC7 | TIM8 CH1 / CH2 (AF3), encoder mode |
//! | linear encoder A / B | PB6 / PB7 | TIM4 CH1 / CH2 (AF2), encoder mode |
//! | pixel / line / frame clock out | PA1 / PA2 / PA3 | GPIO push-pull ([`trigger_pins`]) |
//! | external trigger in | PA6 | GPIO input, pull-down ([`trigger_pins`]) |
//!
//! The `emulator` feature builds these modules for QEMU's `netduinoplus2`, which models
//! neither RCC, DMA, the DAC, the flash interface, CCM RAM nor TIM2's update interrupt: the
//! clock stays on HSI ([`clocks`]), the control tick comes from SysTick instead of TIM2
//! ([`control_timer`]), the link receives by RXNE interrupt and transmits polled instead of
//! by DMA ([`usart`]), the parameter record is read-only, and the coarse axis (`dual-stage`)
//! is the library's model of it. [`setup`] has the table; every difference is chosen there
//! or below, by type, never in the application.
#![allow(unsafe_code)]

pub mod adc;
pub mod ccm;
pub mod clocks;
pub mod coarse_stage;
pub mod control_timer;
pub mod dac;
pub mod param_flash;
pub mod pins;
pub mod profile;
pub mod reset_cause;
pub mod safe_state;
pub mod setpoint_adc;
pub mod setup;
pub mod tick;
pub mod trigger_pins;
pub mod usart;
pub mod watchdog;
