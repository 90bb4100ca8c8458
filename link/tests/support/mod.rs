//! Shared by the link tests.

pub mod fake_board;
