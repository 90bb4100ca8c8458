//! `twinstack-identify`: fitting hysteresis models to measured data, calibrating a board over
//! its link, tuning its feedback, and the `f64` reference every model is checked against.
//!
//! * [`mod@reference`] — the `f64` reference of every model, the specification the library's
//!   fixed-point code is checked against; [`accuracy`] — the fixed-point vs `f64` error table.
//! * [`stage_model`] — an identified model as the board runs it (scaling, sensor sign and lag),
//!   run over whole records in fixed point and in the `f64` reference.
//! * [`identification`] — fitting P–I, generalised P–I, Bouc–Wen, Duhem and creep models, and
//!   choosing among them on held-out data; [`param_file`] — the versioned parameter file.
//! * [`calibrate`] — one-command calibration over the board link: stream the
//!   [`excitation`], record, identify, load, store, verify on the [`trajectory`] records.
//! * [`excitation`] — the drive an identification is recorded on (calibrate's, and the
//!   laboratory stage's): the major loop, concentric minor loops, and on request nested
//!   off-centre loops and a multisine.
//! * [`tune`] — the feedback gains from a measured frequency response, checked against
//!   margins; [`zero_order_hold`] — the exact discretisation its loop model and the simulated
//!   stage share.
//! * [`golden`] — golden vectors: generating them, and checking them against the `f64` tick.
//! * [`preview`] — a planned trajectory shaped ahead of time so that the stage's resonance
//!   (what `tune` fits) does not ring at its corners.
//! * [`budget`] — what a configuration costs the control tick and the highest rate the board
//!   admits it at.

pub mod accuracy;
pub mod budget;
pub mod calibrate;
pub mod excitation;
pub mod golden;
pub mod identification;
pub mod param_file;
pub mod preview;
pub mod reference;
pub mod stage_model;
pub mod trajectory;
pub mod tune;
pub mod zero_order_hold;
