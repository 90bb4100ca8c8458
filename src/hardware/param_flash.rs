//! Where the parameter record lives: the start of flash sector 11 (`memory.x` keeps the image
//! out of it), and [`FlashStorage`], which writes it. The record format and its checks are in
//! [`crate::config::param_store`].

use crate::config::param_store::{RecordStorage, StorageError, MAX_RECORD};

/// Address of flash sector 11 (128 KiB).
pub const PARAM_SECTOR_ADDRESS: usize = 0x080E_0000;

/// The bytes the loader examines: the first [`MAX_RECORD`] bytes of the sector (a record
/// never extends past them).
pub fn record_window() -> &'static [u8] {
    // SAFETY: the address is inside the STM32F405's 1 MiB of memory-mapped flash, which is
    // always readable; memory.x reserves the sector, so nothing in the image aliases it. The
    // sector changes only in `FlashStorage::write` (`&mut self`), while no slice handed out
    // by `FlashStorage::read` (`&self`) is alive; the boot-time reader is done by then.
    unsafe { core::slice::from_raw_parts(PARAM_SECTOR_ADDRESS as *const u8, MAX_RECORD) }
}

/// Flash sector number of the parameter record.
const PARAM_SECTOR: u8 = 11;
/// Flash key sequence (RM0090 §3.5.1).
const UNLOCK_KEYS: [u32; 2] = [0x4567_0123, 0xCDEF_89AB];
/// Polls of BSY before an operation is given up: far above the sector erase's 2 s maximum
/// (the loop runs only when the CPU is not stalled on the flash, i.e. at least 6 cycles an
/// iteration at 168 MHz).
const BUSY_SPIN_LIMIT: u32 = 400_000_000;

fn flash() -> &'static stm32f4xx_hal::pac::flash::RegisterBlock {
    // SAFETY: only `FlashStorage` (one instance, owned by the command handler) touches the
    // flash interface's CR, KEYR and SR after start-up; the clock set-up wrote ACR (wait
    // states) before, and ACR is not touched here.
    unsafe { &*stm32f4xx_hal::pac::FLASH::ptr() }
}

/// The parameter sector as writable storage (the board image; QEMU does not model the flash
/// interface, so the emulator image uses read-only storage).
///
/// A write erases sector 11 (128 KiB: about 1 s, at most 2 s, at 32-bit parallelism on the
/// board's 3.3 V), programs the record word by word and reads it back. While the sector
/// erases, every fetch from flash stalls — the control tick included — so the DAC holds its
/// last output and the watchdog is stretched for the duration
/// ([`super::watchdog::stretch_for_flash_write`]). The command handler refuses a store while
/// the stream or the waveform runs (`Busy`).
pub struct FlashStorage {
    _private: (),
}

impl FlashStorage {
    /// The storage; call once.
    pub fn new() -> Self {
        Self { _private: () }
    }
}

impl Default for FlashStorage {
    fn default() -> Self {
        Self::new()
    }
}

fn wait_not_busy() -> Result<(), StorageError> {
    let f = flash();
    let mut spins = 0u32;
    while f.sr().read().bsy().bit_is_set() {
        spins += 1;
        if spins >= BUSY_SPIN_LIMIT {
            return Err(StorageError::WriteFailed);
        }
    }
    let sr = f.sr().read();
    if sr.wrperr().bit_is_set()
        || sr.pgaerr().bit_is_set()
        || sr.pgperr().bit_is_set()
        || sr.pgserr().bit_is_set()
    {
        return Err(StorageError::WriteFailed);
    }
    Ok(())
}

fn erase_and_program(record: &[u8]) -> Result<(), StorageError> {
    let f = flash();
    wait_not_busy()?;
    // Clear old error flags (write 1 to clear).
    f.sr().write(|w| {
        w.wrperr()
            .clear_bit_by_one()
            .pgaerr()
            .clear_bit_by_one()
            .pgperr()
            .clear_bit_by_one()
            .pgserr()
            .clear_bit_by_one()
    });
    for key in UNLOCK_KEYS {
        f.keyr().write(|w| w.key().set(key));
    }
    if f.cr().read().lock().bit_is_set() {
        return Err(StorageError::WriteFailed);
    }
    // Sector erase, 32-bit parallelism.
    f.cr()
        .write(|w| unsafe { w.ser().set_bit().snb().bits(PARAM_SECTOR).psize().bits(2) });
    f.cr().modify(|_, w| w.strt().set_bit());
    wait_not_busy()?;
    // Program, a word at a time (the tail padded with the erased value 0xFF).
    f.cr()
        .write(|w| unsafe { w.pg().set_bit().psize().bits(2) });
    for (i, chunk) in record.chunks(4).enumerate() {
        let mut word = [0xFFu8; 4];
        word[..chunk.len()].copy_from_slice(chunk);
        let address = (PARAM_SECTOR_ADDRESS + 4 * i) as *mut u32;
        // SAFETY: inside the parameter sector (record ≤ MAX_RECORD bytes), which memory.x
        // keeps out of the image; PG is set, so the store programs the word.
        unsafe { core::ptr::write_volatile(address, u32::from_le_bytes(word)) };
        wait_not_busy()?;
    }
    Ok(())
}

impl RecordStorage for FlashStorage {
    fn read(&self) -> &[u8] {
        record_window()
    }

    fn write(&mut self, record: &[u8]) -> Result<(), StorageError> {
        if record.len() > MAX_RECORD {
            return Err(StorageError::WriteFailed);
        }
        super::watchdog::stretch_for_flash_write();
        let written = erase_and_program(record);
        // Whatever happened: programming off, flash locked, watchdog back to its timeout.
        flash().cr().write(|w| w.lock().set_bit());
        super::watchdog::restore_timeout();
        written?;
        // Read back with volatile loads: the bytes changed behind any earlier borrow.
        let base = PARAM_SECTOR_ADDRESS as *const u8;
        let same = record.iter().enumerate().all(|(i, &b)| {
            // SAFETY: i < record.len() ≤ MAX_RECORD, inside the always-readable sector.
            unsafe { core::ptr::read_volatile(base.add(i)) == b }
        });
        if same {
            Ok(())
        } else {
            Err(StorageError::WriteFailed)
        }
    }
}
