//! The host link, 8N1 at [`BAUD`]: the board profile's USART ([`super::profile::LinkUsart`]:
//! USART1 on PA9/PA10 on the driver board, USART3 on PB10/PB11 — the TX/RX pins — on the
//! Feather), its pins in AF7, and its DMA streams ([`super::profile::LINK_DMA`]). The text below
//! names the driver board's; the Feather's are DMA1 streams 1 (receive) and 3 (transmit),
//! channel 4.
//!
//! **Receive, board:** DMA2 stream 2 (channel 4) copies every received byte into a circular
//! buffer of [`RX_BUFFER_LEN`] bytes; the USART's idle-line interrupt (a gap after a burst) and
//! the stream's half- and full-transfer interrupts call [`UsartRx::drain`], which hands the bytes
//! that arrived since the last call to the frame decoder's queue. No byte costs an interrupt.
//!
//! **Receive, emulator:** QEMU does not model DMA, so each byte raises RXNE and
//! [`UsartRx::drain`] reads the data register.
//!
//! **Transmit, board:** [`DmaTx`], USART1_TX on DMA2 stream 7 (channel 4), two frame buffers:
//! one on the line, one waiting. The command handler's task hands it whole frames (responses
//! first, telemetry in between: [`crate::services::telemetry::FrameLink`]); the stream's
//! transfer-complete interrupt ([`DmaTx::on_complete`]) starts the waiting buffer at once, so
//! the line does not idle between frames and no byte costs the CPU anything.
//!
//! **Transmit, emulator:** QEMU does not model DMA, so [`UsartTx`] sends the same frames
//! through the same trait by polling TXE from the command task, with a bounded wait per byte
//! (3.3 µs a byte at 3 Mbaud on a board).

use stm32f4xx_hal::pac::RCC;

use super::clocks::BusClocks;
use super::profile::LinkUsart;
use crate::board::UartDivider;

/// Baud rate of the host link: 3 Mbaud, exact from the driver board's 84 MHz APB2 (BRR = 28,
/// USARTDIV 1.75 at 16× oversampling) and from the Feather's 42 MHz APB1 (BRR = 0x16,
/// USARTDIV 1.75 at 8× oversampling: 16× cannot go above 2.625 Mbaud there), computed by
/// [`crate::board::UartDivider`], and exact on the common USB–serial adapters (FT232R's and
/// CP2102N's top rate; FT232H's 12 MHz ÷ 4): 300 000 bytes/s each way, of which 100 000
/// setpoints/s in packed batches take 213 542 (docs: the streaming chapter). (The emulator's
/// 16 MHz HSI cannot divide down to it; QEMU ignores the divider.)
pub const BAUD: u32 = crate::protocol::LINK_BAUD;
/// Size of the DMA receive ring, bytes. Bursts longer than this between two drains lose data;
/// the half-transfer and transfer-complete interrupts drain at every half ring, so a drain may
/// start up to `RX_BUFFER_LEN / 2` byte times (256 bytes: 853 µs at 3 Mbaud, 85 ticks at
/// 100 kHz) after its interrupt before the DMA overwrites an unread byte.
pub const RX_BUFFER_LEN: usize = 512;
/// Polls of TXE per byte before [`UsartTx::write_all`] gives up (≈ 3 ms at 168 MHz, far more
/// than one byte time at [`BAUD`]).
const TX_SPIN_LIMIT: u32 = 100_000;

fn regs() -> &'static stm32f4xx_hal::pac::usart1::RegisterBlock {
    // SAFETY: the link's USART is owned by this module after `configure` consumed it; TX and RX use
    // disjoint parts of it (TX: DR writes, TXE; RX: DR reads, RXNE/IDLE), which the hardware
    // keeps apart (separate transmit and receive data registers behind DR).
    unsafe { &*LinkUsart::ptr() }
}

/// The transmit half, polled (the emulator's: QEMU models no DMA).
pub struct UsartTx {
    _private: (),
}

/// The transmitter did not take a byte in time (it never happens on working hardware).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TxTimeout;

/// Frames [`UsartTx`] cut short because the transmitter stopped taking bytes, since power-up.
static TX_TIMEOUTS: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// Frames the polled transmitter cut short on a [`TxTimeout`] since power-up (each one also
/// logged): 0 on working hardware.
pub fn tx_timeouts() -> u32 {
    TX_TIMEOUTS.load(core::sync::atomic::Ordering::Relaxed)
}

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

impl crate::services::telemetry::FrameLink for UsartTx {
    /// Always: the frame is written out before `send_frame` returns.
    fn ready(&mut self) -> bool {
        true
    }

    /// Writes the frame out, polling TXE at most `TX_SPIN_LIMIT` times a byte; a
    /// transmitter that stops taking bytes (never on working hardware) loses the rest of the
    /// frame, which the host sees as a bad frame, and the loss is counted ([`tx_timeouts`])
    /// and logged.
    fn send_frame(&mut self, frame: &[u8]) -> bool {
        if self.write_all(frame).is_err() {
            let n = TX_TIMEOUTS.fetch_add(1, core::sync::atomic::Ordering::Relaxed) + 1;
            defmt::warn!(
                "link transmitter stalled: frame cut short ({=u32} so far)",
                n
            );
        }
        true
    }
}

/// The divider for [`BAUD`] from the link USART's bus clock. The emulator's 16 MHz HSI cannot
/// reach 3 Mbaud (QEMU ignores the divider): it gets the fastest divider there is (8×,
/// USARTDIV 1).
fn divider(pclk_hz: u32) -> UartDivider {
    UartDivider::for_rate(pclk_hz, BAUD).unwrap_or(UartDivider {
        brr: 0x10,
        over8: true,
        baud_hz: pclk_hz / 8,
    })
}

/// Enables the link's USART (and, on a board, its receive DMA stream) and returns its two
/// halves. Its TX/RX pins must already be in AF7.
pub fn configure(
    usart: LinkUsart,
    #[cfg(not(feature = "emulator"))] dma: super::profile::LinkDma,
    rcc: &RCC,
    clocks: &BusClocks,
) -> (UsartTx, UsartRx) {
    let pclk_hz = enable_link_usart(rcc, clocks);
    let divider = divider(pclk_hz);
    usart.brr().write(|w| unsafe { w.bits(divider.brr) });
    #[cfg(not(feature = "emulator"))]
    let rx = UsartRx::start_dma(dma, rcc, &usart, divider.over8);
    #[cfg(feature = "emulator")]
    let rx = {
        usart.cr1().write(|w| {
            w.over8()
                .bit(divider.over8)
                .ue()
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

/// Clears DMA `stream`'s five flags (FEIF, DMEIF, TEIF, HTIF, TCIF): streams 0–3 in `LIFCR`,
/// 4–7 in `HIFCR`, at bits 0, 6, 16, 22 (RM0090 §10.5.3). Write-1-to-clear: no other stream's
/// flag changes.
#[cfg(not(feature = "emulator"))]
fn clear_stream_flags(dma: &stm32f4xx_hal::pac::dma2::RegisterBlock, stream: usize) {
    const OFFSET: [u32; 4] = [0, 6, 16, 22];
    let bits = 0b11_1101 << OFFSET[stream % 4];
    if stream < 4 {
        dma.lifcr().write(|w| unsafe { w.bits(bits) });
    } else {
        dma.hifcr().write(|w| unsafe { w.bits(bits) });
    }
}

#[cfg(not(feature = "emulator"))]
pub use dma_rx::UsartRx;
#[cfg(not(feature = "emulator"))]
pub use dma_tx::DmaTx;

#[cfg(not(feature = "emulator"))]
mod dma_tx {
    use core::cell::UnsafeCell;

    use stm32f4xx_hal::pac::RCC;

    use super::{clear_stream_flags, regs, UsartTx};
    use crate::command_handler::MAX_RESPONSE;
    use crate::hardware::profile::{LinkDma, LINK_DMA};

    /// The DMA stream carrying the link's TX (DMA2 stream 7 on the driver board).
    const STREAM: usize = LINK_DMA.tx;
    /// Its channel selection.
    const CHANNEL: u8 = LINK_DMA.channel;
    /// Bytes of one frame buffer: the largest response frame.
    const TX_BUFFER_LEN: usize = MAX_RESPONSE;

    /// The two frame buffers, in SRAM (the DMA cannot reach CCM RAM). The DMA reads the buffer on
    /// the line; only [`DmaTx::send_frame`] writes, and only the other one.
    struct TxBuffers(UnsafeCell<[[u8; TX_BUFFER_LEN]; 2]>);
    // SAFETY: written only through `DmaTx` (one owner, behind the RTIC resource lock), into
    // the buffer the DMA is not reading; the DMA only reads.
    unsafe impl Sync for TxBuffers {}
    static TX_BUFFERS: TxBuffers = TxBuffers(UnsafeCell::new([[0; TX_BUFFER_LEN]; 2]));

    fn dma() -> &'static stm32f4xx_hal::pac::dma2::RegisterBlock {
        // SAFETY: this module touches only its stream's registers and flags; the receive side
        // ([`super::UsartRx`]) owns another stream, and the flag-clear registers are
        // write-1-to-clear, so neither side's writes touch the other's flags.
        unsafe { &*LinkDma::ptr() }
    }

    /// The link's TX by DMA, double-buffered: one frame on the line, one waiting.
    pub struct DmaTx {
        /// The buffer on the line.
        sending: Option<usize>,
        /// A buffer filled and waiting for the line, with its length.
        waiting: Option<(usize, usize)>,
    }

    impl DmaTx {
        /// Takes over the transmit half (the USART's CR3.DMAT is set by `configure`); the DMA
        /// controller's clock is enabled here too.
        pub fn new(_tx: UsartTx, rcc: &RCC) -> Self {
            super::enable_link_dma(rcc);
            dma().st(STREAM).cr().write(|w| w.en().clear_bit());
            Self {
                sending: None,
                waiting: None,
            }
        }

        /// The transfer-complete interrupt (`DMA2_STREAM7`, `DMA1_STREAM3` on the Feather): the buffer on the line is free;
        /// the waiting one, if any, goes on the line at once.
        pub fn on_complete(&mut self) {
            clear_flags();
            if dma().st(STREAM).cr().read().en().bit_is_set() {
                return; // not done yet (a spurious call)
            }
            self.sending = None;
            if let Some((buffer, len)) = self.waiting.take() {
                self.start(buffer, len);
            }
        }

        fn start(&mut self, buffer: usize, len: usize) {
            let st = dma().st(STREAM);
            clear_flags();
            let base = TX_BUFFERS.0.get() as *const u8;
            // SAFETY: `buffer` is 0 or 1: the offset stays inside the static.
            let address = unsafe { base.add(buffer.min(1) * TX_BUFFER_LEN) } as u32;
            st.par()
                .write(|w| unsafe { w.bits(regs().dr().as_ptr() as u32) });
            st.m0ar().write(|w| unsafe { w.bits(address) });
            st.ndtr()
                .write(|w| unsafe { w.bits(len.min(TX_BUFFER_LEN) as u32) });
            // Memory → peripheral, bytes, memory increment, transfer-complete interrupt.
            st.cr().write(|w| unsafe {
                w.chsel()
                    .bits(CHANNEL)
                    .dir()
                    .memory_to_peripheral()
                    .minc()
                    .set_bit()
                    .tcie()
                    .set_bit()
                    .en()
                    .set_bit()
            });
            self.sending = Some(buffer);
        }
    }

    impl crate::services::telemetry::FrameLink for DmaTx {
        /// A buffer is free: none is waiting for the line.
        fn ready(&mut self) -> bool {
            self.waiting.is_none()
        }

        /// Copies the frame into the free buffer and puts it on the line, or behind the one
        /// there; `false` while both are taken.
        fn send_frame(&mut self, frame: &[u8]) -> bool {
            if self.waiting.is_some() {
                return false;
            }
            let buffer = match self.sending {
                None => 0,
                Some(b) => 1 - b.min(1),
            };
            let len = frame.len().min(TX_BUFFER_LEN);
            let base = TX_BUFFERS.0.get() as *mut u8;
            // SAFETY: the buffer is not the one the DMA reads (`sending`), and `len` fits it.
            unsafe {
                core::ptr::copy_nonoverlapping(
                    frame.as_ptr(),
                    base.add(buffer * TX_BUFFER_LEN),
                    len,
                );
            }
            if self.sending.is_none() {
                self.start(buffer, len);
            } else {
                self.waiting = Some((buffer, len));
            }
            true
        }
    }

    /// Clears the stream's flags.
    fn clear_flags() {
        clear_stream_flags(dma(), STREAM);
    }
}

#[cfg(not(feature = "emulator"))]
mod dma_rx {
    use core::cell::UnsafeCell;

    use stm32f4xx_hal::pac::RCC;

    use super::{clear_stream_flags, regs, RX_BUFFER_LEN};
    use crate::hardware::profile::{LinkDma, LinkUsart, LINK_DMA};

    /// The DMA stream carrying the link's RX (DMA2 stream 2 on the driver board).
    const STREAM: usize = LINK_DMA.rx;
    /// Its channel selection.
    const CHANNEL: u8 = LINK_DMA.channel;

    /// The receive ring; only the DMA writes it, only [`UsartRx::drain`] reads it.
    struct RxRing(UnsafeCell<[u8; RX_BUFFER_LEN]>);
    // SAFETY: the ring is read only through volatile reads in `UsartRx::drain`, which runs in
    // one interrupt priority level; the DMA engine is the only writer.
    unsafe impl Sync for RxRing {}
    static RX_RING: RxRing = RxRing(UnsafeCell::new([0; RX_BUFFER_LEN]));

    /// The receive half: the DMA ring and how far it has been read.
    pub struct UsartRx {
        dma: LinkDma,
        read: usize,
    }

    impl UsartRx {
        pub(super) fn start_dma(dma: LinkDma, rcc: &RCC, usart: &LinkUsart, over8: bool) -> Self {
            super::enable_link_dma(rcc);
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
            // DMA for receive (this stream) and transmit ([`super::DmaTx`]'s).
            usart.cr3().write(|w| w.dmar().set_bit().dmat().set_bit());
            usart.cr1().write(|w| {
                w.over8()
                    .bit(over8)
                    .ue()
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
        /// the USART's and the receive stream's interrupt (`USART1` and `DMA2_STREAM2` on the
        /// driver board, `USART3` and `DMA1_STREAM1` on the Feather). At most one ring's worth of bytes.
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

    /// Clears the stream's flags.
    fn clear_flags(dma: &LinkDma) {
        clear_stream_flags(dma, STREAM);
    }
}

/// The receive half (emulator: RXNE interrupt).
#[cfg(feature = "emulator")]
pub struct UsartRx {
    _private: (),
}

#[cfg(feature = "emulator")]
impl UsartRx {
    /// Hands the received byte(s) to `sink`; call from the link USART's interrupt. Reading DR
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

/// Enables the link USART's clock and returns the bus clock it counts, Hz: USART1 on APB2.
#[cfg(not(feature = "feather"))]
fn enable_link_usart(rcc: &RCC, clocks: &BusClocks) -> u32 {
    rcc.apb2enr().modify(|_, w| w.usart1en().set_bit());
    clocks.pclk2_hz
}
/// Enables the link USART's clock and returns the bus clock it counts, Hz: USART3 on APB1.
#[cfg(feature = "feather")]
fn enable_link_usart(rcc: &RCC, clocks: &BusClocks) -> u32 {
    rcc.apb1enr().modify(|_, w| w.usart3en().set_bit());
    clocks.pclk1_hz
}

/// Enables the link's DMA controller's clock.
#[cfg(all(not(feature = "emulator"), not(feature = "feather")))]
fn enable_link_dma(rcc: &RCC) {
    rcc.ahb1enr().modify(|_, w| w.dma2en().set_bit());
}
/// Enables the link's DMA controller's clock.
#[cfg(all(not(feature = "emulator"), feature = "feather"))]
fn enable_link_dma(rcc: &RCC) {
    rcc.ahb1enr().modify(|_, w| w.dma1en().set_bit());
}
