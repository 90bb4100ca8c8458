//! The host tool's arguments of the figures that run it more than once: the rankings, the
//! identification tables, the lab-stage tracking and the learning runs the registry
//! ([`super::FIGURES`]) names.

/// `auto`'s ranking on each shipped record at the board's two control rates: every candidate's
/// forward, inverse and tracking figures on the validation part, and where it stands.
pub(super) const RANKING_RUNS: &[&[&str]] = &[
    &[
        "identify",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--tick-rate",
        "50000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--tick-rate",
        "100000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--tick-rate",
        "50000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
    &[
        "identify",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--tick-rate",
        "100000",
        "--out",
        "target/figures/identify-ranking.json",
    ],
];

/// The identification page's per-model runs: every model, without and with creep, on each
/// shipped record (fitted on its first cycles, scored on the rest).
pub(super) const IDENTIFY_RUNS: &[&[&str]] = &[
    &[
        "identify",
        "--model",
        "pi",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "pi",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "gpi",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "duhem",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--creep",
        "--data",
        "data/piezo-bipolar-150v-1hz.csv",
        "--fit-until",
        "5.95",
        "--out",
        "target/figures/identify-model.json",
    ],
    &[
        "identify",
        "--model",
        "bouc-wen",
        "--creep",
        "--data",
        "data/micromanipulator-unipolar-3v6-1hz.csv",
        "--fit-until",
        "16",
        "--out",
        "target/figures/identify-model.json",
    ],
];

/// The lab-stage page's runs: `identify`'s default with the textbook and generalised P–I, the
/// models that do not fit the stage, and both P–Is with creep.
pub(super) const LAB_STAGE_RUNS: &[&[&str]] = &[
    &["lab-stage"],
    &["lab-stage", "--model", "duhem,bouc-wen"],
    &["lab-stage", "--model", "pi,gpi", "--creep"],
];

/// The lab stage with its non-idealities taken out, one run each and all four at once: what is
/// left of the generalised P–I + creep's error.
pub(super) const LAB_STAGE_WITHOUT_RUNS: &[&[&str]] = &[
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "creep",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "flexure",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "asymmetry",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "noise",
    ],
    &[
        "lab-stage",
        "--model",
        "gpi",
        "--creep",
        "--without",
        "creep,flexure,asymmetry,noise",
    ],
];

/// The lab stage with its non-idealities taken out one by one, cumulatively: what each costs the
/// textbook P–I.
pub(super) const LAB_STAGE_PI_WITHOUT_RUNS: &[&[&str]] = &[
    &["lab-stage", "--model", "pi", "--without", "noise"],
    &["lab-stage", "--model", "pi", "--without", "creep"],
    &["lab-stage", "--model", "pi", "--without", "creep,flexure"],
    &[
        "lab-stage",
        "--model",
        "pi",
        "--without",
        "creep,flexure,asymmetry",
    ],
];

/// The learning page's runs: each waveform without input shaping (the learning's corner at
/// 18 kHz) and with it (the notch on the simulated stage's resonance as `tune` fits it).
pub(super) const LEARN_RUNS: &[&[&str]] = &[
    &[
        "learn",
        "--waveform",
        "sine:750",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:750",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:200",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:200",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:500",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:500",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:1000",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "sine:1000",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:100",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:100",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:250",
        "--out",
        "target/figures/learning",
    ],
    &[
        "learn",
        "--waveform",
        "triangle:250",
        "--shape-hz",
        "21807",
        "--out",
        "target/figures/learning",
    ],
];

/// The learning curves' runs: the two waveforms the goals are set on, without and with input
/// shaping (the learning page's first four runs).
pub(super) const LEARN_CURVE_RUNS: &[&[&str]] =
    &[LEARN_RUNS[0], LEARN_RUNS[1], LEARN_RUNS[2], LEARN_RUNS[3]];

/// The learning runs of each corner (the robustness filter's, Hz) and notch frequency (Hz):
/// the 750 Hz sine, then the 200 Hz triangle, for each.
macro_rules! notch_runs {
    ($($corner:literal => [$($notch:literal),*]),*) => {
        &[$($(
            &["learn", "--waveform", "sine:750", "--shape-hz", $notch, "--cutoff-hz", $corner],
            &["learn", "--waveform", "triangle:200", "--shape-hz", $notch, "--cutoff-hz", $corner],
        )*)*]
    };
}

/// The notch's robustness: the learning's corner at 22, 23 (the default with shaping) and
/// 24 kHz, the notch placed off the fitted resonance (21 807 Hz) by −2, −1, −0.5, 0, +0.5, +1
/// and +2 % (rounded to the hertz), each on the 750 Hz sine and the 200 Hz triangle.
pub(super) const LEARN_NOTCH_RUNS: &[&[&str]] = notch_runs!(
    "22000" => ["21371", "21589", "21698", "21807", "21916", "22025", "22243"],
    "23000" => ["21371", "21589", "21698", "21807", "21916", "22025", "22243"],
    "24000" => ["21371", "21589", "21698", "21807", "21916", "22025", "22243"]
);
