//! `hal-sim`: the host twin of the twinstack board and the PC-side tools.
pub mod accuracy;
