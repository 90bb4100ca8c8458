//! The image itself (built for the target only; see the crate docs in `main.rs`).

use cortex_m_rt::{entry, exception, ExceptionFrame};
use defmt_rtt as _;
use stm32f4xx_hal::pac;

use twinstack::board::{DacCode, DualDac};
use twinstack::hardware::dac::InternalDac;
use twinstack::hardware::param_flash::PARAM_SECTOR_ADDRESS;
use twinstack::hardware::safe_state;

/// Written to GPIOA's ODR (logged by QEMU) on entry to the panic handler.
const PANIC_MARKER: u32 = 0x0BAD;
/// Written to GPIOA's ODR on entry to the hard-fault handler.
const FAULT_MARKER: u32 = 0xFA17;

/// Tells the test which handler ran (QEMU logs the write to the unmodelled GPIO port).
fn mark(value: u32) {
    // SAFETY: a single store to GPIOA's output data register on the way to a halt.
    unsafe { (*pac::GPIOA::ptr()).odr().write(|w| w.bits(value)) };
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    mark(PANIC_MARKER);
    safe_state::stop_on_panic(info)
}

#[exception]
unsafe fn HardFault(_frame: &ExceptionFrame) -> ! {
    mark(FAULT_MARKER);
    safe_state::stop_on_fault()
}

#[entry]
fn main() -> ! {
    let Some(dp) = pac::Peripherals::take() else {
        panic!("peripherals taken twice")
    };
    let mut dac = InternalDac::new(dp.DAC, &dp.RCC, (DacCode(0x001), DacCode(0x002)));
    safe_state::arm(DacCode(0x123), DacCode(0x456));
    let _ = dac.write_both(DacCode(0x700), DacCode(0x300));
    // SAFETY: the parameter sector is readable flash.
    let fault = unsafe { core::ptr::read_volatile(PARAM_SECTOR_ADDRESS as *const u8) } == 1;
    if fault {
        cortex_m::asm::udf();
    }
    panic!("safe-state probe: deliberate panic");
}
