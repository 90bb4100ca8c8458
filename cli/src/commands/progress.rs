//! Progress bars for the long board commands (`stream`, `record`): drawn on stderr when it is
//! a terminal, hidden otherwise (a pipe, a file, a test), so logs and scripts see only the
//! command's report.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;

/// Whether bars are drawn: stderr is a terminal.
pub fn enabled() -> bool {
    std::io::stderr().is_terminal()
}

/// A bar of `len` `unit`s labelled `what`, or a hidden one when stderr is not a terminal.
pub fn bar(len: u64, what: &str, unit: &str) -> ProgressBar {
    if !enabled() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    let template = format!("{{msg:10}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{eta}})");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(what.to_string());
    bar
}
