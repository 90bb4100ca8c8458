//! Where the parameter record lives: the start of flash sector 11 (`memory.x` keeps the image
//! out of it). The record format and its checks are in [`crate::param_store`].

use crate::param_store::MAX_RECORD;

/// Address of flash sector 11 (128 KiB).
pub const PARAM_SECTOR_ADDRESS: usize = 0x080E_0000;

/// The bytes the loader examines: the first [`MAX_RECORD`] bytes of the sector (a record
/// never extends past them).
pub fn record_window() -> &'static [u8] {
    // SAFETY: the address is inside the STM32F405's 1 MiB of memory-mapped flash, which is
    // always readable; memory.x reserves the sector, so nothing in the image aliases it, and
    // flash does not change under us (the firmware does not write the sector while running).
    unsafe { core::slice::from_raw_parts(PARAM_SECTOR_ADDRESS as *const u8, MAX_RECORD) }
}
