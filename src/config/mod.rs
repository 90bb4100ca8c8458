//! Configuration: what a user sets, how it is checked and kept, and what it costs the tick.
//! Everything here runs off the interrupt; it prepares what the interrupt swaps in.
//!
//! * [`settings`] — the one settings type (physical units, serde): what the wire, the flash
//!   record, parameter files and golden vectors carry, and its `build` into the tick's
//!   fixed-point configuration.
//! * [`param_store`] — the CRC-protected settings record in flash.
//! * [`tick_budget`] — the whole interrupt's predicted worst case, and the refusal of a
//!   configuration that would not fit the control period.

pub mod param_store;
pub mod settings;
pub mod tick_budget;
