//! What `auto` gives on stages the family was not tuned on: the lab stage's variants
//! ([`twinstack_cli::tracking::STAGE_VARIANTS`]: each non-ideality made stronger, weaker or turned
//! around, and two combinations), identified and tracked as on the default stage.
//!
//! Ignored unless asked for (`cargo xtask test` runs it as its own gate, `cargo test --profile
//! host-opt --workspace --test stage_variants -- --ignored`): 21 stages, each identified with
//! every candidate, take about half a minute optimised and far too long unoptimised.
//!
//! It holds, on every variant, what the default stage's test holds on one: `auto` at most
//! half the textbook P–I's worst error and a quarter of no compensation's; and the number of
//! variants on which it meets the 1 % goal (19 of 21 when this was written; the two it misses
//! are listed in the book, results/lab-stage.md, "Other stages").

use hal_sim::plant::LabStageConfig;
use twinstack_cli::tracking::{
    evaluate_variants, print_variants, Method, EXCITATION, FIT_UNTIL_S, SAMPLE_RATE_HZ,
    STAGE_VARIANTS,
};
use twinstack_identify::identification::{IdentifyOptions, ModelKind};

/// Variants on which `auto`'s worst error must be within the 1 % goal.
const WITHIN_GOAL_AT_LEAST: usize = 19;

#[test]
#[ignore = "slow: run optimised, see the module doc"]
fn auto_holds_on_stages_it_was_not_tuned_on() {
    let base = IdentifyOptions::new(ModelKind::Pi, FIT_UNTIL_S);
    let tables = evaluate_variants(
        &LabStageConfig::new(SAMPLE_RATE_HZ, 1),
        &STAGE_VARIANTS,
        &[Method::Auto(base.candidates()), Method::One(base.clone())],
        None,
        &EXCITATION,
    )
    .unwrap();
    print_variants(&tables, &mut std::io::stdout()).unwrap();
    assert_eq!(tables.len(), STAGE_VARIANTS.len());
    let mut within = Vec::new();
    for v in &tables {
        let worst = |i: usize| {
            let row = &v.table.rows[i];
            assert!(
                row.error.is_none(),
                "{}: {}: {:?}",
                v.variant,
                row.method,
                row.error
            );
            row.worst_max_pct().unwrap()
        };
        // rows: none, auto, the textbook P–I.
        let (none, auto, pi) = (worst(0), worst(1), worst(2));
        assert!(
            auto <= 0.5 * pi,
            "{} ({}): auto {auto:.2} % against the textbook P-I's {pi:.2} %",
            v.variant,
            v.settings
        );
        assert!(
            auto <= 0.25 * none,
            "{} ({}): auto {auto:.2} % against no compensation's {none:.2} %",
            v.variant,
            v.settings
        );
        if auto <= 1.0 {
            within.push(v.variant);
        }
    }
    assert!(
        within.len() >= WITHIN_GOAL_AT_LEAST,
        "auto within 1 % on {} variants ({within:?}), fewer than {WITHIN_GOAL_AT_LEAST}",
        within.len()
    );
}

/// A variant names only fields the stage has, and each makes a valid stage.
#[test]
fn every_variant_is_a_valid_stage() {
    for (name, changes) in STAGE_VARIANTS {
        let c = twinstack_cli::tracking::variant_config(
            &LabStageConfig::new(SAMPLE_RATE_HZ, 1),
            changes,
        )
        .unwrap_or_else(|e| panic!("{name}: {e}"));
        c.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(
            c == LabStageConfig::new(SAMPLE_RATE_HZ, 1),
            changes.is_empty(),
            "{name}: changes the stage exactly when it lists a change"
        );
    }
}
