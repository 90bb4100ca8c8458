//! The CSV files a lab exports, read by `identify`/`predict`/`compensate`
//! ([`MeasuredData`]) and `stream` ([`setpoint_file`]): tabs, semicolons (with decimal
//! commas), quoted headers, a byte-order mark, unit-suffixed and capitalised header names,
//! CRLF line ends and other column names (`--columns`) all read to the same data as the plain
//! CSV; a bad cell still names the file, line and column.

use std::path::Path;
use std::process::Command;
use twinstack_link::measured_data::{ColumnNames, Columns, DataError, MeasuredData};
use twinstack_link::setpoint_file::{self, SetpointUnits};

const N: usize = 12;

/// `(t, u, x)` rows: exact binary fractions, so a decimal comma reads to the same value.
fn values() -> Vec<(f64, f64, f64)> {
    (0..N)
        .map(|i| {
            (
                i as f64 * 0.5,
                10.0 + i as f64 * 2.25,
                -3.0 + i as f64 * 0.75,
            )
        })
        .collect()
}

/// The record with header cells `names` joined by `sep`, numbers by `sep` (with `,` as the
/// decimal mark when `decimal_comma`), lines ending in `eol`.
fn record(names: [&str; 3], sep: &str, decimal_comma: bool, eol: &str) -> String {
    let num = |v: f64| {
        let s = format!("{v}");
        if decimal_comma {
            s.replace('.', ",")
        } else {
            s
        }
    };
    let mut s = format!("# exported{eol}{}{eol}", names.join(sep));
    for (t, u, x) in values() {
        s.push_str(&format!("{}{sep}{}{sep}{}{eol}", num(t), num(u), num(x)));
    }
    s
}

fn plain() -> String {
    record(["t", "u", "x"], ",", false, "\n")
}

fn variants() -> Vec<(&'static str, String)> {
    vec![
        ("tabs", record(["t", "u", "x"], "\t", false, "\n")),
        ("semicolons", record(["t", "u", "x"], ";", false, "\n")),
        (
            "semicolons, decimal commas",
            record(["t", "u", "x"], ";", true, "\n"),
        ),
        (
            "tabs, decimal commas",
            record(["t", "u", "x"], "\t", true, "\n"),
        ),
        (
            "quoted header",
            record(["\"t\"", "\"u\"", "\"x\""], ",", false, "\n"),
        ),
        ("byte-order mark", format!("\u{feff}{}", plain())),
        (
            "unit suffixes",
            record(["t [s]", "u (V)", "x [um]"], ",", false, "\n"),
        ),
        ("capitals", record(["T", "U", "X"], ",", false, "\n")),
        ("spaces", record([" t ", " u", "x "], " , ", false, "\n")),
        ("CRLF", record(["t", "u", "x"], ",", false, "\r\n")),
        (
            "all at once",
            format!(
                "\u{feff}{}",
                record(["\"T [s]\"", "\"U (V)\"", "\"x[um]\""], ";", true, "\r\n")
            ),
        ),
    ]
}

fn measured(text: &str, names: &ColumnNames) -> Result<MeasuredData, DataError> {
    MeasuredData::parse_with(Path::new("in.csv"), text, Columns::TimeDriveOutput, names)
}

#[test]
fn every_variant_reads_to_the_plain_record() {
    let want = measured(&plain(), &ColumnNames::default()).expect("plain");
    assert_eq!(want.len(), N);
    assert_eq!(want.u.as_ref().unwrap()[3], 16.75);
    for (what, text) in variants() {
        let got = measured(&text, &ColumnNames::default())
            .unwrap_or_else(|e| panic!("{what}: {e}\n{text}"));
        assert_eq!(got, want, "{what}");
    }
}

#[test]
fn other_column_names_are_mapped_with_columns() {
    let want = measured(&plain(), &ColumnNames::default()).unwrap();
    let text = record(
        ["Time [s]", "Piezo voltage (V)", "Sensor [um]"],
        "\t",
        false,
        "\n",
    );
    // Without the map the message says what the header has and how to map it.
    let e = measured(&text, &ColumnNames::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("in.csv:2: header has no column `t`")
            && e.contains("Time [s], Piezo voltage (V), Sensor [um]")
            && e.contains("--columns t=NAME"),
        "{e}"
    );
    let names: ColumnNames = "t=time, u=PIEZO VOLTAGE,x=sensor [um]".parse().unwrap();
    assert_eq!(measured(&text, &names).unwrap(), want);
    // A mapped name that is not there is named in the error.
    let names: ColumnNames = "x=gauge".parse().unwrap();
    let e = measured(&plain(), &names).unwrap_err().to_string();
    assert!(
        e.contains("header has no column `x` named `gauge` (from --columns"),
        "{e}"
    );
    for bad in ["t", "y=a", "t=a,t=b", "u="] {
        assert!(bad.parse::<ColumnNames>().is_err(), "{bad}");
    }
}

#[test]
fn a_bad_cell_still_names_file_line_and_column() {
    for (what, text) in variants() {
        // Line 5 is the third data row (line 1 a comment, line 2 the header).
        let mut lines: Vec<String> = text.split_inclusive('\n').map(String::from).collect();
        let sep = if text.contains('\t') {
            "\t"
        } else if text.contains(';') {
            ";"
        } else {
            ","
        };
        let eol = if text.contains("\r\n") { "\r\n" } else { "\n" };
        lines[4] = format!("1{sep}abc{sep}2{eol}");
        let e = measured(&lines.concat(), &ColumnNames::default())
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("in.csv:5: column `"), "{what}: {e}");
        assert!(e.ends_with("`abc` is not a number"), "{what}: {e}");
        assert!(
            e.contains("column `u`") || e.contains("column `U") || e.contains("column `u ("),
            "{what}: {e}"
        );
    }
}

/// The setpoint file: the same variants, with `t` and `setpoint` columns.
#[test]
fn setpoint_files_read_the_same_in_every_variant() {
    let read = |text: &str| {
        setpoint_file::parse(
            Path::new("sp.csv"),
            text,
            SetpointUnits::Normalised,
            50_000.0,
            None,
        )
    };
    let rows = |names: [&str; 2], sep: &str, decimal_comma: bool| {
        let mut s = format!("{}\n", names.join(sep));
        for i in 0..N {
            let (t, v) = (i as f64 * 4e-5, -0.5 + i as f64 * 0.0625);
            let v = format!("{v}");
            let v = if decimal_comma {
                v.replace('.', ",")
            } else {
                v
            };
            s.push_str(&format!("{t}{sep}{v}\n"));
        }
        s
    };
    let want = read(&rows(["t", "setpoint"], ",", false)).expect("plain");
    assert_eq!(want.divider_from_t, Some(2));
    for (what, text) in [
        ("tabs", rows(["t", "setpoint"], "\t", false)),
        ("semicolons", rows(["t", "setpoint"], ";", true)),
        ("quoted", rows(["\"t\"", "\"setpoint\""], ",", false)),
        (
            "BOM",
            format!("\u{feff}{}", rows(["t", "setpoint"], ",", false)),
        ),
        ("units", rows(["t [s]", "Setpoint (norm.)"], ",", false)),
    ] {
        let got = read(&text).unwrap_or_else(|e| panic!("{what}: {e}"));
        assert_eq!(got, want, "{what}");
    }
    let e = read("\u{feff}\"t [s]\";\"setpoint\"\n0;0,1\n0,00002;zero\n")
        .unwrap_err()
        .to_string();
    assert_eq!(e, "sp.csv:3: column `setpoint`: `zero` is not a number");
}

/// `twinstack predict --columns` on a tab-separated export with a BOM writes what the plain
/// file gives; a bad `--columns` is a usage error.
#[test]
fn predict_reads_an_export_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let model = twinstack_identify::stage_model::StageModel {
        hysteresis: twinstack_identify::stage_model::Hysteresis::Pi(
            match twinstack::config::settings::representative_pi(16).unwrap() {
                twinstack::config::settings::Model::PrandtlIshlinskii(p) => p,
                other => panic!("{other:?}"),
            },
        ),
        scaling: twinstack::Scaling::new(0.0, 140.0, -10.0, 80.0).unwrap(),
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
    };
    let params = dir.path().join("p.json");
    std::fs::write(
        &params,
        twinstack_identify::param_file::ParamFile::from_model(&model, "um", None).to_json(),
    )
    .unwrap();
    let plain_csv = dir.path().join("plain.csv");
    std::fs::write(&plain_csv, plain()).unwrap();
    let export = dir.path().join("export.tsv");
    std::fs::write(
        &export,
        format!(
            "\u{feff}{}",
            record(["Time [s]", "Drive (V)", "Gauge [um]"], "\t", false, "\r\n")
        ),
    )
    .unwrap();
    let run = |data: &Path, out: &str, extra: &[&str]| {
        let out = dir.path().join(out);
        let o = Command::new(env!("CARGO_BIN_EXE_twinstack"))
            .args(["predict", "--params"])
            .arg(&params)
            .arg("--data")
            .arg(data)
            .arg("--out")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        (o, out)
    };
    let (o, a) = run(&plain_csv, "a.csv", &[]);
    assert!(o.status.success(), "{o:?}");
    let (o, b) = run(&export, "b.csv", &["--columns", "t=time,u=drive"]);
    assert!(o.status.success(), "{o:?}");
    assert_eq!(
        std::fs::read_to_string(a).unwrap(),
        std::fs::read_to_string(b).unwrap()
    );
    let (o, _) = run(&export, "c.csv", &["--columns", "y=drive"]);
    assert_eq!(o.status.code(), Some(2), "{o:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--columns") && err.contains("t, u and x"),
        "{err}"
    );
}
