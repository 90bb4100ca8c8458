//! The main job end to end: the simulated stage, identification, and tracking through the
//! same control tick as the firmware.

use twinstack_cli::demo::{run, DemoOptions};

#[test]
fn inverse_pi_cuts_the_differential_stages_tracking_error_at_least_fivefold() {
    let dir = tempfile::tempdir().unwrap();
    let report = run(&DemoOptions {
        cycles: 24,
        out_dir: dir.path().to_path_buf(),
        progress: false,
        ..DemoOptions::default()
    })
    .unwrap();
    let none = report.tracking("differential", "none").unwrap();
    let pi = report.tracking("differential", "inverse P–I").unwrap();
    let duhem = report.tracking("differential", "inverse Duhem").unwrap();
    assert!(
        none.rms_pct >= 5.0 * pi.rms_pct,
        "inverse P–I: {:.2} % RMS against {:.2} % without compensation",
        pi.rms_pct,
        none.rms_pct
    );
    assert!(
        none.rms_pct > 2.0 * duhem.rms_pct,
        "inverse Duhem must help too"
    );
    // The first paper's finding: the differential configuration is modelled far better.
    for model in ["Duhem", "P–I, N = 9"] {
        let row = |c: &str| {
            report
                .modelling
                .iter()
                .find(|r| r.configuration == c && r.model == model)
                .unwrap()
                .rms_pct
        };
        assert!(row("differential") < row("unidirectional"), "{model}");
    }
    for f in &report.figures {
        let bytes = std::fs::read(f).unwrap();
        assert!(
            bytes.starts_with(b"\x89PNG"),
            "{} is not a PNG",
            f.display()
        );
    }
}

#[test]
fn demo_refuses_bad_flags_with_a_clear_error() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(["demo", "--rate", "1000000", "--quiet"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--rate"), "{err}");
}
