//! The stored golden vectors are right, not only consistent: their outputs agree with the `f64`
//! reference tick within the documented fixed-point bounds, and their inputs and
//! configurations are what the generator makes from the committed parameter files.
//! (`tests/golden.rs` at the repository root checks that the tick, on the host and on the
//! board, reproduces the outputs bit for bit.)

use twinstack::config::settings::Mode;
use twinstack_golden::format::encode_record;
use twinstack_golden::{TickInput, TickOutput, VectorSet, VectorSets, MAX_RECIPE};
use twinstack_identify::golden::reference_tick::{
    check, Agreement, CODE_BOUND, DRIVE_BOUND_LSB16, ESTIMATE_BOUND_LSB16,
};
use twinstack_identify::golden::{default_dir, generate, sets, REGENERATE, VECTOR_FILE};

fn stored() -> Vec<u8> {
    let path = default_dir().join(VECTOR_FILE);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn parse(file: &[u8]) -> Vec<VectorSet<'_>> {
    VectorSets::new(file)
        .collect::<Result<Vec<_>, _>>()
        .unwrap_or_else(|e| panic!("vectors.bin: {e:?}; regenerate with `{REGENERATE}`"))
}

#[test]
fn stored_outputs_agree_with_the_f64_reference_tick() {
    let file = stored();
    for set in parse(&file) {
        let a = check(&set).unwrap();
        eprintln!(
            "{:<20} drive {:.4} LSB16  estimate {:.4} LSB16  code {:.4}  ambiguous {}  holds {}",
            a.name, a.drive_lsb16, a.estimate_lsb16, a.code_error, a.ambiguous, a.integrator_holds
        );
        assert_eq!(a.ticks, set.ticks() as usize);
        assert!(
            a.holds(),
            "set {}: outside the f64 reference's bounds (drive ≤ {DRIVE_BOUND_LSB16} LSB16, \
             estimate ≤ {ESTIMATE_BOUND_LSB16} LSB16, codes ≤ {CODE_BOUND}): {a:?}",
            set.name()
        );
        // Ambiguous range/slew decisions are rare; many would mean the check is too lax.
        assert!(a.ambiguous < 20, "set {}: {a:?}", set.name());
        // Every closed-loop set drives the feedback into its anti-windup hold.
        let settings = set.recipe().unwrap().settings;
        if settings.feedback.is_some() && settings.mode == Mode::ClosedLoop {
            assert!(a.integrator_holds > 10, "set {}: {a:?}", set.name());
        }
    }
}

#[test]
fn the_generator_reproduces_the_stored_inputs_and_configurations() {
    let file = stored();
    let stored = parse(&file);
    let defs = sets::definitions(&default_dir()).unwrap();
    let (generated, _) = generate::generate_all(&defs).unwrap();
    let names: Vec<&str> = stored.iter().map(|s| s.name()).collect();
    let want: Vec<&str> = generated.iter().map(|g| g.name).collect();
    assert_eq!(
        names, want,
        "the set list changed; regenerate with `{REGENERATE}`"
    );
    for (s, g) in stored.iter().zip(&generated) {
        assert_eq!(
            s.recipe().unwrap(),
            defs.iter().find(|d| d.name == g.name).unwrap().recipe,
            "set {}: its configuration changed; regenerate with `{REGENERATE}`",
            s.name()
        );
        if let Some(k) = s.inputs().zip(&g.inputs).position(|(a, b)| a != *b) {
            panic!(
                "set {}: input of tick {k} differs (the scenario, the sensor model or the tick \
                 changed); regenerate with `{REGENERATE}`",
                s.name()
            );
        }
    }
}

/// The check is not vacuous: one drive off by one LSB16, or one code off by one, fails it.
#[test]
fn a_wrong_output_fails_the_reference_check() {
    let file = stored();
    let set = parse(&file)
        .into_iter()
        .find(|s| s.name() == "ipi16-pi-closed")
        .expect("set ipi16-pi-closed");
    let inputs: Vec<TickInput> = set.inputs().collect();
    let mut buf = [0u8; MAX_RECIPE];
    let recipe = set.recipe().unwrap();
    let recipe = recipe.encode(&mut buf).unwrap();
    let tamper = |k: usize, f: &dyn Fn(&mut TickOutput)| {
        let mut outputs: Vec<TickOutput> = set.outputs().collect();
        f(&mut outputs[k]);
        let mut bytes = Vec::new();
        encode_record(
            set.name(),
            set.config_fingerprint(),
            recipe,
            &inputs,
            &outputs,
            &mut bytes,
        )
        .unwrap();
        let s = VectorSets::new(&bytes).next().unwrap().unwrap();
        check(&s).unwrap()
    };
    let a = tamper(1000, &|o| o.drive += 1 << 15);
    assert_eq!(a.first_violation, Some(1000), "{a:?}");
    let a = tamper(700, &|o| o.left += 1);
    assert_eq!(a.first_violation, Some(700), "{a:?}");
    let a = tamper(300, &|o| {
        o.flags ^= twinstack::control::TickFlags::DAC_ERROR
    });
    assert_eq!(a.first_flag_mismatch.map(|m| m.0), Some(300), "{a:?}");
    let untouched = tamper(0, &|_| {});
    assert!(untouched.holds());
}

/// Set `name`'s stored inputs and outputs, against its recipe changed by `f`, through the
/// reference check.
fn recheck_with(
    file: &[u8],
    name: &str,
    f: &dyn Fn(&mut twinstack::config::settings::Settings),
) -> Agreement {
    let set = parse(file)
        .into_iter()
        .find(|s| s.name() == name)
        .unwrap_or_else(|| panic!("set {name}"));
    let inputs: Vec<TickInput> = set.inputs().collect();
    let outputs: Vec<TickOutput> = set.outputs().collect();
    let mut recipe = set.recipe().unwrap();
    f(&mut recipe.settings);
    let mut b = [0u8; MAX_RECIPE];
    let b = recipe.encode(&mut b).unwrap();
    let mut bytes = Vec::new();
    encode_record(
        set.name(),
        set.config_fingerprint(),
        b,
        &inputs,
        &outputs,
        &mut bytes,
    )
    .unwrap();
    let s = VectorSets::new(&bytes).next().unwrap().unwrap();
    check(&s).unwrap()
}

/// The check follows the feedback's and the sensor's settings: the same stored outputs against
/// the recipe with another proportional or integral gain, or without the drift limit, fail it.
#[test]
fn the_reference_check_depends_on_the_feedback_settings() {
    let file = stored();
    let recheck = |f: &dyn Fn(&mut twinstack::config::settings::Settings)| {
        recheck_with(&file, "ipi16-pi-closed", f)
    };
    assert!(recheck(&|_| {}).holds());
    let a = recheck(&|s| s.feedback.as_mut().unwrap().kp *= 1.1);
    assert!(a.first_violation.is_some(), "kp: {a:?}");
    let a = recheck(&|s| s.feedback.as_mut().unwrap().ki *= 1.1);
    assert!(a.first_violation.is_some(), "ki: {a:?}");
    let a = recheck(&|s| s.sensor.as_mut().unwrap().drift_limit = None);
    assert!(a.flag_mismatches > 100, "drift limit: {a:?}");
}

/// The check follows the mode and the start: the bypassed set with a compensator, rechecked as
/// if it ran open loop, or as if it had started from the bias rather than its zero safe state,
/// fails it.
#[test]
fn the_reference_check_depends_on_the_mode_and_the_safe_state() {
    let file = stored();
    let recheck = |f: &dyn Fn(&mut twinstack::config::settings::Settings)| {
        recheck_with(&file, "ipi16-duhem-bypass", f)
    };
    assert!(recheck(&|_| {}).holds());
    let a = recheck(&|s| s.mode = Mode::OpenLoop);
    assert!(a.first_violation.is_some(), "open loop: {a:?}");
    let a = recheck(&|s| s.drive.safe_state = twinstack::control::drive::SafeState::Bias);
    assert_eq!(a.first_violation, Some(0), "safe state: {a:?}");
}

/// The check runs the creep: the creep set rechecked without its creep, or with one mode's
/// weight changed, fails it.
#[test]
fn the_reference_check_depends_on_the_creep() {
    let file = stored();
    let recheck = |f: &dyn Fn(&mut twinstack::config::settings::Settings)| {
        recheck_with(&file, "ipi16-pi-creep-closed", f)
    };
    assert!(recheck(&|_| {}).holds());
    let a = recheck(&|s| s.creep = None);
    assert!(a.first_violation.is_some(), "no creep: {a:?}");
    let a = recheck(&|s| s.creep.as_mut().unwrap().weights[0] += 0.01);
    assert!(a.first_violation.is_some(), "weight: {a:?}");
}
