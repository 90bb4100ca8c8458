//! USART1 (PA9 TX, PA10 RX, AF7), 8N1 at [`BAUD`]: the host link.
//!
//! **Receive, board:** DMA2 stream 2 (channel 4) copies every received byte into a circular
//! buffer of [`RX_BUFFER_LEN`] bytes; the USART's idle-line interrupt (a gap after a burst) and
//! the stream's half- and full-transfer interrupts call [`UsartRx::drain`], which hands the bytes
//! that arrived since the last call to the frame decoder's queue. No byte costs an interrupt.
//!
//! **Receive, emulator:** QEMU does not model DMA, so each byte raises RXNE and
//! [`UsartRx::drain`] reads the data register.
//!
//! **Transmit:** [`UsartTx::write_all`] polls TXE from the lowest-priority task (the command
//! handler), with a bounded wait per byte: 5 µs a byte at 2 Mbaud, so an `Ack` costs the task
//! about 50 µs and the largest response (a recorder chunk) under 2 ms.

use stm32f4xx_hal::pac::{RCC, USART1};

use super::clocks::BusClocks;

/// Baud rate of the host link: 2 Mbaud, exact from the board's 84 MHz APB2 (BRR = 42). (The
/// emulator's 16 MHz HSI cannot divide down to it; QEMU ignores the divider.)
pub const BAUD: u32 = 2_000_000;
/// Size of the DMA receive ring, bytes. Bursts longer than this between two drains lose data;
/// the half-transfer interrupt drains at every half ring, so it would take
/// `RX_BUFFER_LEN / 2` bytes inside one interrupt latency.
pub const RX_BUFFER_LEN: usize = 256;
/// Polls of TXE per byte before [`UsartTx::write_all`] gives up (≈ 3 ms at 168 MHz, far more
/// than one byte time at [`BAUD`]).
const TX_SPIN_LIMIT: u32 = 100_000;

fn regs() -> &'static stm32f4xx_hal::pac::usart1::RegisterBlock {
    // SAFETY: USART1 is owned by this module after `configure` consumed it; TX and RX use
    // disjoint parts of it (TX: DR writes, TXE; RX: DR reads, RXNE/IDLE), which the hardware
    // keeps apart (separate transmit and receive data registers behind DR).
    unsafe { &*USART1::ptr() }
}

/// The transmit half.
pub struct UsartTx {
    _private: (),
}

/// The transmitter did not take a byte in time (it never happens on working hardware).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TxTimeout;

impl UsartTx {
    /// Sends `bytes`, waiting for TXE before each one.
    pub fn write_all(&mut self, bytes: &[u8]) -> Result<(), TxTimeout> {
        let u = regs();
        for &b in bytes {
            let mut spins = 0;
            while u.sr().read().txe().bit_is_clear() {
                spins += 1;
                if spins >= TX_SPIN_LIMIT {
                    return Err(TxTimeout);
                }
            }
            u.dr().write(|w| unsafe { w.bits(b as u16) });
        }
        Ok(())
    }
}

/// Enables USART1 (and, on the board, DMA2 stream 2) and returns its two halves. PA9/PA10 must
/// already be in AF7.
pub fn configure(
    usart: USART1,
    #[cfg(not(feature = "emulator"))] dma: stm32f4xx_hal::pac::DMA2,
    rcc: &RCC,
    clocks: &BusClocks,
) -> (UsartTx, UsartRx) {
    rcc.apb2enr().modify(|_, w| w.usart1en().set_bit());
    let brr = (clocks.pclk2_hz + BAUD / 2) / BAUD;
    usart
        .brr()
        .write(|w| unsafe { w.bits(brr.min(u16::MAX as u32) as u16) });
    #[cfg(not(feature = "emulator"))]
    let rx = UsartRx::start_dma(dma, rcc, &usart);
    #[cfg(feature = "emulator")]
    let rx = {
        usart.cr1().write(|w| {
            w.ue()
                .set_bit()
                .te()
                .set_bit()
                .re()
                .set_bit()
                .rxneie()
                .set_bit()
        });
        UsartRx { _private: () }
    };
    (UsartTx { _private: () }, rx)
}

#[cfg(not(feature = "emulator"))]
pub use dma_rx::UsartRx;

#[cfg(not(feature = "emulator"))]
mod dma_rx {
    use core::cell::UnsafeCell;

    use stm32f4xx_hal::pac::{DMA2, RCC, USART1};

    use super::{regs, RX_BUFFER_LEN};

    /// DMA2 stream carrying USART1_RX.
    const STREAM: usize = 2;
    /// Its channel selection.
    const CHANNEL: u8 = 4;

    /// The receive ring; only the DMA writes it, only [`UsartRx::drain`] reads it.
    struct RxRing(UnsafeCell<[u8; RX_BUFFER_LEN]>);
    // SAFETY: the ring is read only through volatile reads in `UsartRx::drain`, which runs in
    // one interrupt priority level; the DMA engine is the only writer.
    unsafe impl Sync for RxRing {}
    static RX_RING: RxRing = RxRing(UnsafeCell::new([0; RX_BUFFER_LEN]));

    /// The receive half: the DMA ring and how far it has been read.
    pub struct UsartRx {
        dma: DMA2,
        read: usize,
    }

    impl UsartRx {
        pub(super) fn start_dma(dma: DMA2, rcc: &RCC, usart: &USART1) -> Self {
            rcc.ahb1enr().modify(|_, w| w.dma2en().set_bit());
            let st = dma.st(STREAM);
            st.cr().write(|w| w.en().clear_bit());
            st.par()
                .write(|w| unsafe { w.bits(usart.dr().as_ptr() as u32) });
            st.m0ar()
                .write(|w| unsafe { w.bits(RX_RING.0.get() as u32) });
            st.ndtr().write(|w| unsafe { w.bits(RX_BUFFER_LEN as u32) });
            clear_flags(&dma);
            // Peripheral → memory, bytes, memory increment, circular, HT + TC interrupts.
            st.cr().write(|w| unsafe {
                w.chsel()
                    .bits(CHANNEL)
                    .minc()
                    .set_bit()
                    .circ()
                    .set_bit()
                    .htie()
                    .set_bit()
                    .tcie()
                    .set_bit()
                    .en()
                    .set_bit()
            });
            usart.cr3().write(|w| w.dmar().set_bit());
            usart.cr1().write(|w| {
                w.ue()
                    .set_bit()
                    .te()
                    .set_bit()
                    .re()
                    .set_bit()
                    .idleie()
                    .set_bit()
            });
            Self { dma, read: 0 }
        }

        /// Hands every byte received since the last call to `sink`, oldest first, and clears
        /// the interrupt causes (USART idle line, DMA half / full transfer). Call it from both
        /// the `USART1` and the `DMA2_STREAM2` interrupt. At most one ring's worth of bytes.
        pub fn drain(&mut self, mut sink: impl FnMut(u8)) {
            let u = regs();
            // IDLE clears by reading SR, then DR.
            if u.sr().read().idle().bit_is_set() {
                let _ = u.dr().read();
            }
            clear_flags(&self.dma);
            let remaining = self.dma.st(STREAM).ndtr().read().bits() as usize;
            let written = (RX_BUFFER_LEN - remaining.min(RX_BUFFER_LEN)) % RX_BUFFER_LEN;
            let base = RX_RING.0.get() as *const u8;
            let mut i = self.read;
            let mut n = 0;
            while i != written && n < RX_BUFFER_LEN {
                // SAFETY: i < RX_BUFFER_LEN; volatile because the DMA writes behind our back.
                sink(unsafe { core::ptr::read_volatile(base.add(i)) });
                i = (i + 1) % RX_BUFFER_LEN;
                n += 1;
            }
            self.read = i;
        }
    }

    /// Clears stream 2's flags (LIFCR bits 16–21).
    fn clear_flags(dma: &DMA2) {
        dma.lifcr().write(|w| unsafe { w.bits(0b11_1101 << 16) });
    }
}

/// The receive half (emulator: RXNE interrupt).
#[cfg(feature = "emulator")]
pub struct UsartRx {
    _private: (),
}

#[cfg(feature = "emulator")]
impl UsartRx {
    /// Hands the received byte(s) to `sink`; call from the `USART1` interrupt. Reading DR
    /// clears RXNE. Bounded: at most 16 bytes per call.
    pub fn drain(&mut self, mut sink: impl FnMut(u8)) {
        let u = regs();
        for _ in 0..16 {
            if u.sr().read().rxne().bit_is_clear() {
                break;
            }
            sink(u.dr().read().bits() as u8);
        }
    }
}
