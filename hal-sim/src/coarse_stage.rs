//! The coarse stage's peripherals, emulated behind the library's board traits: the step/dir
//! output ([`EmulatedStepDir`], a timer emitting a burst of pulses over one coarse period, as
//! TIM1 with its repetition counter does on the board) and the quadrature encoder inputs
//! ([`EmulatedEncoder`], a timer in encoder mode: A/B lines from a quantised position, decoded
//! ×4 into a wrapping 16-bit counter).

use twinstack::board::{QuadratureEncoder, StepBurst, StepDir, StepDirection};
use twinstack::dual_stage::coarse_axis::QuadratureDecoder;

/// Why the emulated step output refused a burst.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StepDirError {
    /// The previous burst is still running.
    Busy,
    /// More pulses than a burst holds.
    TooManySteps(u16),
}

/// A step/dir output whose pulses are spread evenly over `ticks` fine periods.
#[derive(Clone, Debug)]
pub struct EmulatedStepDir {
    ticks: u32,
    max_steps: u16,
    burst: Option<(StepBurst, u32)>,
    /// Microstep position the driver has counted.
    position: i64,
    /// Pulses emitted in total.
    pulses: u64,
    /// DIR changes between bursts.
    reversals: u64,
    last_direction: Option<StepDirection>,
}

impl EmulatedStepDir {
    /// An output whose bursts last `ticks` fine periods (one coarse period), each of at most
    /// `max_steps` pulses.
    pub fn new(ticks: u32, max_steps: u16) -> Self {
        Self {
            ticks: ticks.max(1),
            max_steps,
            burst: None,
            position: 0,
            pulses: 0,
            reversals: 0,
            last_direction: None,
        }
    }

    /// One fine period: emits the pulses due in it; returns the driver's microstep position.
    pub fn advance(&mut self) -> i64 {
        if let Some((burst, elapsed)) = &mut self.burst {
            let n = burst.steps as u64;
            let before = n * *elapsed as u64 / self.ticks as u64;
            *elapsed += 1;
            let after = n * *elapsed as u64 / self.ticks as u64;
            let pulses = (after - before) as i64;
            self.position += match burst.direction {
                StepDirection::Forward => pulses,
                StepDirection::Reverse => -pulses,
            };
            self.pulses += pulses as u64;
            if *elapsed >= self.ticks {
                self.burst = None;
            }
        }
        self.position
    }

    /// Microstep position the driver has counted.
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Pulses emitted in total.
    pub fn pulses(&self) -> u64 {
        self.pulses
    }

    /// Times DIR changed between bursts.
    pub fn reversals(&self) -> u64 {
        self.reversals
    }
}

impl StepDir for EmulatedStepDir {
    type Error = StepDirError;

    fn max_steps_per_burst(&self) -> u16 {
        self.max_steps
    }

    fn emit(&mut self, burst: StepBurst) -> Result<(), StepDirError> {
        if self.burst.is_some() {
            return Err(StepDirError::Busy);
        }
        if burst.steps > self.max_steps {
            return Err(StepDirError::TooManySteps(burst.steps));
        }
        if self.last_direction.is_some_and(|d| d != burst.direction) {
            self.reversals += 1;
        }
        self.last_direction = Some(burst.direction);
        self.burst = Some((burst, 0));
        Ok(())
    }
}

/// Most edges one [`EmulatedEncoder::move_to`] replays one by one.
const MAX_EDGES_PER_MOVE: u64 = 1 << 20;

/// A quadrature encoder on a timer in encoder mode: a position quantised to `resolution`,
/// turned into A/B line levels edge by edge and counted by the library's ×4 decoder.
#[derive(Clone, Debug)]
pub struct EmulatedEncoder {
    resolution: f64,
    lines_position: i64,
    decoder: QuadratureDecoder,
}

impl EmulatedEncoder {
    /// An encoder with `resolution` (position units per count, > 0) at `position`.
    pub fn new(resolution: f64, position: f64) -> Self {
        let count = (position / resolution).floor() as i64;
        let (a, b) = QuadratureDecoder::lines_at(count);
        Self {
            resolution,
            lines_position: count,
            decoder: QuadratureDecoder::new(a, b),
        }
    }

    /// The scale moves to `position`: every edge between the last position and this one is
    /// seen in order (the input filter of a timer sees each edge at these speeds).
    pub fn move_to(&mut self, position: f64) {
        let target = (position / self.resolution).floor() as i64;
        if target.abs_diff(self.lines_position) > MAX_EDGES_PER_MOVE {
            // Far more edges than a timer could see in one period: they are missed, as on the
            // board; the lines jump.
            let (a, b) = QuadratureDecoder::lines_at(target);
            self.decoder.update(a, b);
            self.lines_position = target;
            return;
        }
        while self.lines_position != target {
            self.lines_position += (target - self.lines_position).signum();
            let (a, b) = QuadratureDecoder::lines_at(self.lines_position);
            self.decoder.update(a, b);
        }
    }

    /// Counts since start (signed), as the decoder counted them.
    pub fn counted(&self) -> i64 {
        self.decoder.count()
    }

    /// Edges the decoder missed.
    pub fn missed(&self) -> u32 {
        self.decoder.missed()
    }
}

impl QuadratureEncoder for EmulatedEncoder {
    fn count(&mut self) -> u16 {
        self.decoder.counter_register()
    }
}
