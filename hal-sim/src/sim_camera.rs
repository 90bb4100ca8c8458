//! A simulated camera on the simulated board's trigger input: what drives a TTL-stepped
//! sequence ([`twinstack::sources::sequence`]) on `--port sim` and `twinstack virtual-board`.
//!
//! Wired as a lab wires one: the camera's TTL output (a pulse at the end of each frame's
//! exposure) onto the board's trigger input (PA6). Like an acquisition program that arms the
//! stage and then starts the camera, it starts its frames on the tick a sequence is armed (or
//! a scan or the stream is armed to start on the input's edge), and stops when that is over
//! (the sequence disarmed, the scan or the stream started) or after `frames` frames.
//!
//! Two timings:
//! * **free-running** (`on_settled = false`): one frame every `period_ticks`, whatever the
//!   stage does — frames faster than the settle time give early edges;
//! * **triggered by the settled output** (`on_settled = true`, the board's settled output →
//!   the camera's trigger input): a frame starts when the settled output is high and ends
//!   `period_ticks` later with the pulse, so no edge is early.

/// The camera's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraConfig {
    /// Ticks from a frame's start to its TTL pulse (the exposure; in free-running mode the
    /// frame period), at least 2.
    pub period_ticks: u32,
    /// Frames, then the camera stops; 0: until the sequence is disarmed.
    pub frames: u32,
    /// Start each frame on the settled output (else free-running).
    pub on_settled: bool,
}

impl CameraConfig {
    /// A camera at `frame_hz` frames a second on a board ticking at `tick_rate_hz`; refused
    /// (naming the value) when the frame period is under 2 ticks or not finite.
    ///
    /// ```
    /// use hal_sim::sim_camera::CameraConfig;
    /// let c = CameraConfig::at_rate(1000.0, 50_000.0, 10, false).unwrap();
    /// assert_eq!(c.period_ticks, 50);
    /// assert!(CameraConfig::at_rate(f64::NAN, 50_000.0, 10, false).is_err());
    /// assert!(CameraConfig::at_rate(40_000.0, 50_000.0, 10, false).is_err());
    /// ```
    pub fn at_rate(
        frame_hz: f64,
        tick_rate_hz: f64,
        frames: u32,
        on_settled: bool,
    ) -> Result<Self, String> {
        let ticks = tick_rate_hz / frame_hz;
        if !(frame_hz.is_finite() && frame_hz > 0.0 && ticks.is_finite()) {
            return Err(format!(
                "camera rate {frame_hz}: must be a positive number of frames a second"
            ));
        }
        if !(2.0..=u32::MAX as f64).contains(&ticks.round()) {
            return Err(format!(
                "camera rate {frame_hz} Hz: a frame must last at least 2 ticks of the board's {tick_rate_hz} Hz (at most {} Hz)",
                tick_rate_hz / 2.0
            ));
        }
        Ok(Self {
            period_ticks: ticks.round() as u32,
            frames,
            on_settled,
        })
    }
}

/// The camera's state, stepped once before each tick ([`SimCamera::step`]).
#[derive(Clone, Debug)]
pub struct SimCamera {
    config: CameraConfig,
    running: bool,
    /// Ticks to the end of the frame under way (0: between frames).
    left: u32,
    /// Ticks the TTL pulse stays high.
    high: u32,
    /// Frames whose pulse was sent since the camera started.
    sent: u32,
    was_armed: bool,
}

impl SimCamera {
    /// An idle camera.
    pub fn new(config: CameraConfig) -> Self {
        Self {
            config,
            running: false,
            left: 0,
            high: 0,
            sent: 0,
            was_armed: false,
        }
    }

    /// Frames sent since the camera last started.
    pub fn frames_sent(&self) -> u32 {
        self.sent
    }

    /// One tick: `armed` whether the board's sequence is armed (or a source waits for the
    /// input's edge), `settled` its settled output (as the last tick left it). Returns the TTL output's level for this tick.
    pub fn step(&mut self, armed: bool, settled: bool) -> bool {
        if armed && !self.was_armed {
            self.running = true;
            self.sent = 0;
            self.left = 0;
        }
        self.was_armed = armed;
        if !armed {
            self.running = false;
        }
        if self.high > 0 {
            self.high -= 1;
        }
        let done = self.config.frames != 0 && self.sent >= self.config.frames;
        if self.running && !done {
            if self.left == 0 && (!self.config.on_settled || settled) {
                self.left = self.config.period_ticks;
            }
            if self.left > 0 {
                self.left -= 1;
                if self.left == 0 {
                    // End of the frame: a pulse of half the period (at least one tick).
                    self.high = (self.config.period_ticks / 2).max(1);
                    self.sent += 1;
                }
            }
        }
        self.high > 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_free_running_camera_pulses_once_a_period_after_the_arming() {
        let mut c = SimCamera::new(CameraConfig {
            period_ticks: 4,
            frames: 3,
            on_settled: false,
        });
        assert!(!c.step(false, false));
        let levels: Vec<bool> = (0..16).map(|_| c.step(true, false)).collect();
        let rises: Vec<usize> = (1..levels.len())
            .filter(|&k| levels[k] && !levels[k - 1])
            .collect();
        assert_eq!(rises, vec![3, 7, 11]);
        assert!(levels[3], "the first frame ends on the 4th tick");
        assert_eq!(c.frames_sent(), 3);
    }

    #[test]
    fn a_camera_on_the_settled_output_waits_for_it() {
        let mut c = SimCamera::new(CameraConfig {
            period_ticks: 2,
            frames: 0,
            on_settled: true,
        });
        for _ in 0..10 {
            assert!(!c.step(true, false));
        }
        assert!(!c.step(true, true));
        assert!(c.step(true, false));
        assert_eq!(c.frames_sent(), 1);
    }
}
