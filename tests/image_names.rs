//! The board image and the emulator image are two binaries with two names (so `cargo
//! build-fw` and `cargo build-emu` never write the same file, and the wrong one is never
//! booted by mistake). Checked where the names are decided: the cargo aliases and the `[[bin]]`
//! targets. (That each image reports which it is, is checked by `tests/emulator.rs` and
//! `cli/tests/emulator_link.rs` in QEMU, and by the handler's status test here.)

use std::path::Path;

fn read(path: &str) -> String {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join(path);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// The command line of the cargo alias `name` in `.cargo/config.toml`.
fn alias(name: &str) -> String {
    let config = read(".cargo/config.toml");
    let line = config
        .lines()
        .find(|l| l.trim_start().starts_with(&format!("{name} =")))
        .unwrap_or_else(|| panic!("no alias {name} in .cargo/config.toml"));
    line.split_once('=')
        .unwrap()
        .1
        .trim()
        .trim_matches('"')
        .to_string()
}

/// The value of `--bin` in a command line.
fn bin(command: &str) -> &str {
    let mut words = command.split_whitespace();
    words.by_ref().find(|w| *w == "--bin");
    words
        .next()
        .unwrap_or_else(|| panic!("no --bin in {command}"))
}

#[test]
fn build_fw_and_build_emu_write_different_files() {
    let fw = alias("build-fw");
    let emu = alias("build-emu");
    assert_eq!(bin(&fw), "twinstack-fw", "{fw}");
    assert_eq!(bin(&emu), "twinstack-emu", "{emu}");
    assert!(emu.contains("--features emulator"), "{emu}");
    assert!(!fw.contains("emulator"), "{fw}");
    // Flashing runs the board image.
    assert_eq!(bin(&alias("flash-fw")), "twinstack-fw");
}

#[test]
fn the_emulator_binary_exists_only_with_the_emulator_feature() {
    let manifest = read("Cargo.toml");
    let targets: Vec<&str> = manifest.split("[[bin]]").skip(1).collect();
    let emu = targets
        .iter()
        .find(|t| t.contains("name = \"twinstack-emu\""))
        .expect("a [[bin]] twinstack-emu in Cargo.toml");
    assert!(emu.contains("required-features = [\"emulator\"]"), "{emu}");
    // The board binary refuses to build as an emulator image under its own name.
    let fw = read("src/bin/twinstack-fw.rs");
    assert!(
        fw.contains("#[cfg(all(target_os = \"none\", feature = \"emulator\"))]\ncompile_error!"),
        "src/bin/twinstack-fw.rs no longer refuses the emulator feature"
    );
}

#[test]
fn the_feather_images_have_their_own_names_and_features() {
    let fw = alias("build-fw-feather");
    let emu = alias("build-emu-feather");
    assert_eq!(bin(&fw), "twinstack-feather", "{fw}");
    assert_eq!(bin(&emu), "twinstack-feather-emu", "{emu}");
    assert!(
        fw.contains("--features feather") && !fw.contains("emulator"),
        "{fw}"
    );
    assert!(emu.contains("--features emulator,feather"), "{emu}");
    assert_eq!(bin(&alias("flash-fw-feather")), "twinstack-feather");
    let manifest = read("Cargo.toml");
    let target = |name: &str| {
        manifest
            .split("[[bin]]")
            .skip(1)
            .find(|t| t.contains(&format!("name = \"{name}\"\n")))
            .unwrap_or_else(|| panic!("no [[bin]] {name} in Cargo.toml"))
            .to_string()
    };
    assert!(target("twinstack-feather").contains("required-features = [\"feather\"]"));
    assert!(
        target("twinstack-feather-emu").contains("required-features = [\"feather\", \"emulator\"]")
    );
    // Each image refuses the other profile's feature under its name.
    for (file, feature) in [
        ("src/bin/twinstack-fw.rs", "feature = \"feather\""),
        ("src/bin/twinstack-emu.rs", "feature = \"feather\""),
        ("src/bin/twinstack-feather.rs", "feature = \"emulator\""),
    ] {
        let text = read(file);
        assert!(
            text.contains(&format!(
                "#[cfg(all(target_os = \"none\", {feature}))]\ncompile_error!"
            )),
            "{file} no longer refuses {feature}"
        );
    }
}

#[test]
fn the_dual_stage_images_have_their_own_names_and_features() {
    let fw = alias("build-fw-dual");
    let emu = alias("build-emu-dual");
    assert_eq!(bin(&fw), "twinstack-fw-dual", "{fw}");
    assert_eq!(bin(&emu), "twinstack-emu-dual", "{emu}");
    assert!(
        fw.contains("--features dual-stage") && !fw.contains("emulator"),
        "{fw}"
    );
    assert!(emu.contains("--features emulator,dual-stage"), "{emu}");
    let manifest = read("Cargo.toml");
    let target = |name: &str| {
        manifest
            .split("[[bin]]")
            .skip(1)
            .find(|t| t.contains(&format!("name = \"{name}\"\n")))
            .unwrap_or_else(|| panic!("no [[bin]] {name} in Cargo.toml"))
            .to_string()
    };
    assert!(target("twinstack-fw-dual").contains("required-features = [\"dual-stage\"]"));
    assert!(
        target("twinstack-emu-dual").contains("required-features = [\"emulator\", \"dual-stage\"]")
    );
    // The piezo-only images refuse the coarse axis under their names.
    for file in ["src/bin/twinstack-fw.rs", "src/bin/twinstack-emu.rs"] {
        assert!(
            read(file).contains(
                "#[cfg(all(target_os = \"none\", feature = \"dual-stage\"))]\ncompile_error!"
            ),
            "{file} no longer refuses dual-stage"
        );
    }
}

/// The RTIC application is one shell for every image: what differs per target is chosen in
/// the library (`hardware::setup`), and per image only the interrupt bindings each binary
/// passes, so the shared application has no feature switch.
#[test]
fn the_shared_application_has_no_feature_switch() {
    let app = read("src/bin/firmware/app.rs");
    for feature in ["emulator", "dual-stage", "feather"] {
        assert!(
            !app.contains(&format!("feature = \"{feature}\"")),
            "src/bin/firmware/app.rs switches on {feature}"
        );
    }
}
