//! `hal-sim`: the host twin of the twinstack board and the PC-side tools.
//!
//! * [`plant`] — the dual-stack piezo stage (coupled and `K_0 → ∞` models, exact
//!   discretisation) with "truth" hysteresis per stack.
//! * [`converters`] — emulated DACs, amplifiers, sensor and ADCs, including the external SPI
//!   chips (DAC8562/3, ADS8689) at the wire level.
//! * [`sim_board`] — [`sim_board::SimBoard`]: all of it behind the library's board traits.

pub mod converters;
pub mod plant;
pub mod sim_board;
