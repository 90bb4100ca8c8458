//! The flash check: the settings in force stored, recalled and read back; what flash held
//! before is put back.
use super::*;

/// The top-level fields of two settings that differ.
fn differing_fields(a: &Settings, b: &Settings) -> Vec<String> {
    let (a, b) = (serde_json::to_value(a), serde_json::to_value(b));
    match (a, b) {
        (Ok(serde_json::Value::Object(a)), Ok(serde_json::Value::Object(b))) => a
            .iter()
            .filter(|(k, v)| b.get(*k) != Some(v))
            .map(|(k, _)| k.clone())
            .collect(),
        _ => vec!["(unreadable)".to_string()],
    }
}

pub(super) fn flash(client: &mut BoardClient) -> anyhow::Result<CheckResult> {
    let check = CheckName::Flash;
    let in_force = retry(client, |c| c.read_params())?;
    // What flash holds: recalled (which puts it in force), read, then the settings in force
    // go back.
    let stored = match retry(client, |c| c.recall_params()) {
        Ok(()) => {
            let s = retry(client, |c| c.read_params())?;
            retry(client, |c| c.load_params(&in_force))?;
            Some(s)
        }
        Err(e) if nack_of(&e) == Some(NackReason::NothingStored) => None,
        Err(e) if nack_of(&e) == Some(NackReason::NoStorage) => {
            return Ok(CheckResult::skip(
                check,
                "the board has no parameter storage".to_string(),
            ))
        }
        Err(e) => return Err(e.into()),
    };
    let figures = |ok: bool| {
        serde_json::json!({
            "stored_before": stored.is_some(),
            "recalled_equal": ok,
        })
    };
    match retry(client, |c| c.store_params(in_force.mode)) {
        Ok(()) => {}
        Err(e) if nack_of(&e) == Some(NackReason::NoStorage) => {
            return Ok(CheckResult::skip(
                check,
                "the board has no parameter storage (it says so: the QEMU image models no flash \
                 interface)"
                    .to_string(),
            ))
        }
        Err(e) if nack_of(&e) == Some(NackReason::StoreFailed) => {
            let lost = if stored.is_some() {
                "the settings stored before may be lost (the board boots on its defaults if so)"
            } else {
                "flash held no settings before"
            };
            return Ok(CheckResult::fail(
                check,
                format!("writing the settings in force to flash failed (erase, program or read-back); {lost}"),
                "the parameter sector is worn, write-protected (option bytes) or the supply sagged during the write: check the option bytes with probe-rs, the board's 3.3 V under load, and store again (twinstack load --params FILE --store MODE)",
                figures(false),
            ));
        }
        Err(e) => return Err(e.into()),
    }
    retry(client, |c| c.recall_params())?;
    let recalled = retry(client, |c| c.read_params())?;
    let equal = recalled == in_force;
    // What flash held goes back: those settings stored (in their mode), then the settings
    // in force loaded again.
    let restored = match &stored {
        Some(s) => {
            let put_back = retry(client, |c| c.load_params(s))
                .and_then(|()| retry(client, |c| c.store_params(s.mode)));
            let again = retry(client, |c| c.load_params(&in_force));
            put_back
                .and(again)
                .map(|()| "the settings stored before were stored again")
        }
        None if equal => retry(client, |c| c.load_params(&in_force)).map(|()| {
            "flash held no settings before and now holds the settings in force (the \
                 protocol has no erase): the board boots on them"
        }),
        None => {
            retry(client, |c| c.load_params(&in_force)).map(|()| "flash held no settings before")
        }
    };
    let restored = restored
        .map(str::to_string)
        .unwrap_or_else(|e| format!("putting back what flash held failed: {e}"));
    if !equal {
        return Ok(CheckResult::fail(
            check,
            format!(
                "the settings recalled differ from those stored ({}); {restored}",
                differing_fields(&in_force, &recalled).join(", ")
            ),
            "the record read back is not the one written: a flash or firmware fault; reflash the current image and store again",
            figures(false),
        ));
    }
    Ok(CheckResult::pass(
        check,
        format!("the settings in force were stored, recalled and read back equal; {restored}"),
        figures(true),
    ))
}
