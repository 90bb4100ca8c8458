//! The hysteresis and creep models, in fixed point: each one's forward form (the observer,
//! drive in, displacement out) and its inverse (the compensator, setpoint in, drive out),
//! with their physical (`f64`) parameters. These run in the interrupt, inside the control law.
//!
//! * [`play_operator`] — the play (backlash) operator, the building block of P–I.
//! * [`prandtl_ishlinskii`] — forward and analytic-inverse Prandtl–Ishlinskii models.
//! * [`generalised_pi`] — the generalised (asymmetric) P–I: a P–I followed by a monotone
//!   dead-zone map, and its analytic inverse.
//! * [`duhem`] — Duhem forward observer and inverse Duhem compensator.
//! * [`bouc_wen`] — generalised (asymmetric) Bouc–Wen observer and its inverse-multiplicative
//!   compensator.
//! * [`creep`] — the creep operator (log-spaced first-order modes) in series with a
//!   hysteresis model, and its exact inverse.
//! * [`params`] — the models' physical (`f64`) parameters and their own checks.

pub mod bouc_wen;
pub mod creep;
pub mod duhem;
pub mod generalised_pi;
pub mod params;
pub mod play_operator;
pub mod prandtl_ishlinskii;
