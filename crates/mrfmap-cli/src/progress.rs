//! Progress bars (indicatif) that respect `--quiet` and stay invisible off a terminal.

use std::sync::atomic::{AtomicBool, Ordering};

use indicatif::{ProgressBar, ProgressStyle};

static QUIET: AtomicBool = AtomicBool::new(false);

/// Silences every bar made after this call.
pub fn set_quiet(quiet: bool) {
    QUIET.store(quiet, Ordering::Relaxed);
}

/// A bar over `len` steps labelled `what`; without a length (a recording read as it comes),
/// a count of the steps done.
pub fn bar(len: Option<usize>, what: &str) -> ProgressBar {
    if QUIET.load(Ordering::Relaxed) {
        return ProgressBar::hidden();
    }
    let bar = match len {
        Some(len) => ProgressBar::new(len as u64).with_style(
            ProgressStyle::with_template("{msg:>12} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}")
                .expect("static template")
                .progress_chars("=> "),
        ),
        None => ProgressBar::no_length().with_style(
            ProgressStyle::with_template("{msg:>12} {pos} done {elapsed_precise} ({per_sec})")
                .expect("static template"),
        ),
    };
    bar.set_message(what.to_string());
    bar
}

/// The library's build loop reported on bars like [`bar`]'s, one per stage.
#[derive(Default)]
pub struct Bars {
    bar: Option<ProgressBar>,
}

impl mrfmap::pipeline::Progress for Bars {
    fn stage(&mut self, what: &str, total: Option<usize>) {
        self.end();
        self.bar = Some(bar(total, what));
    }

    fn advance(&mut self, done: usize, total: Option<usize>) {
        if let Some(b) = &self.bar {
            if let Some(total) = total.filter(|&t| b.length() != Some(t as u64)) {
                b.set_length(total as u64);
            }
            b.set_position(done as u64);
        }
    }

    fn status(&mut self, text: &str) {
        if let Some(b) = &self.bar {
            b.set_message(text.to_string());
        }
    }

    fn end(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}
