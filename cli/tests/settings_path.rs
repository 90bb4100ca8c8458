//! Settings by path as a user runs them: `twinstack settings --schema`, `get` and `set` on the
//! simulated board (through its validation and reload) and in a parameter file, and every
//! wrong path or value refused with the path named, exit 1, nothing changed.

#[path = "support/tool.rs"]
mod tool;

use tool::{ok, twinstack};

const SIM: [&str; 6] = [
    "--port",
    "sim",
    "--link-latency-ms",
    "0",
    "--link-jitter-ms",
    "0",
];

fn refused(args: &[&str], needle: &str) {
    let o = twinstack(args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
    assert!(err.contains(needle), "{args:?}: {err:?} lacks {needle:?}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn the_schema_lists_the_paths_a_user_sets() {
    let schema = ok(&["settings", "--schema"]);
    for line in [
        "/feedback/kp",
        "/drive/slew_rate",
        "/mode",
        "/compensator/Duhem/alpha",
    ] {
        assert!(
            schema.lines().any(|l| l.starts_with(line)),
            "{line} missing:\n{schema}"
        );
    }
    let json: serde_json::Value =
        serde_json::from_str(&ok(&["settings", "--schema", "--json"])).unwrap();
    assert!(json.as_array().unwrap().len() > 40);
}

#[test]
fn set_on_the_board_goes_through_its_load_and_reads_back_what_it_holds() {
    let mut args = vec!["set", "/drive/slew_rate", "2000"];
    args.extend(SIM);
    assert_eq!(
        ok(&args).trim(),
        "the board holds /drive/slew_rate = 2000.0"
    );
    let mut args = vec!["set", "/mode", "ClosedLoop"];
    args.extend(SIM);
    assert!(ok(&args).contains("\"ClosedLoop\""));
    // The board's own limits: refused by the board, naming the field and its limit.
    let mut args = vec!["set", "/drive/max_voltage", "1000"];
    args.extend(SIM);
    refused(&args, "max_voltage must be at most 150");
    // Refused on the host before anything is sent: a path that names nothing, a wrong type.
    let mut args = vec!["set", "/drive/slew", "3"];
    args.extend(SIM);
    refused(&args, "`/drive` has no `slew`");
    let mut args = vec!["set", "/drive/slew_rate", "fast"];
    args.extend(SIM);
    refused(&args, "/drive/slew_rate");
    let mut args = vec!["set", "/shaping/q", "0.7"];
    args.extend(SIM);
    refused(&args, "`/shaping` is not set");
}

#[test]
fn set_in_a_parameter_file_changes_one_value_and_keeps_the_file_loadable() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("PARAMS.json");
    let source = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../tests/golden/params/micromanipulator-pi8.json"
    );
    std::fs::copy(source, &file).unwrap();
    let f = file.to_str().unwrap();
    let before: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    ok(&["set", "/drive/slew_rate", "1234.5", "--file", f]);
    assert_eq!(
        ok(&["get", "/drive/slew_rate", "--file", f]).trim(),
        "1234.5"
    );
    let after: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    // The settings are the same but for the one value (the file writes every optional part,
    // `null` where it is not set); the rest of the file is as it was.
    let settings = |v: &serde_json::Value| -> twinstack::config::settings::Settings {
        serde_json::from_value(v["settings"].clone()).unwrap()
    };
    let mut expected = settings(&before);
    expected.drive.slew_rate = 1234.5;
    assert_eq!(settings(&after), expected, "only the one value changed");
    for key in [
        "format",
        "version",
        "identification",
        "units",
        "output_sign",
    ] {
        assert_eq!(after[key], before[key], "{key}");
    }
    // A value the file's own checks refuse leaves the file as it was.
    refused(
        &[
            "set",
            "/compensator/PrandtlIshlinskii/weights/0",
            "\"x\"",
            "--file",
            f,
        ],
        "/compensator/PrandtlIshlinskii/weights/0",
    );
    refused(
        &["set", "/ranges/input_max", "-1000", "--file", f],
        "nothing was written",
    );
    let unchanged: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    assert_eq!(unchanged, after);
}

#[test]
fn load_takes_any_setting_by_path() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("PARAMS.json");
    std::fs::copy(
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../tests/golden/params/micromanipulator-pi8.json"
        ),
        &file,
    )
    .unwrap();
    let f = file.to_str().unwrap();
    let mut args = vec!["load", "--params", f, "--set", "/drive/slew", "--clamp"];
    args.extend(SIM);
    let o = twinstack(&args);
    assert_eq!(
        o.status.code(),
        Some(2),
        "a --set without = is a usage error"
    );
    let mut args = vec!["load", "--params", f, "--set", "/drive/slew=3", "--clamp"];
    args.extend(SIM);
    refused(&args, "`/drive` has no `slew`");
}
