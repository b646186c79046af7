//! How far a long job has come: the one event every long function of the library reports
//! through (dataset generation and loading, evaluation, the initialiser's data), and, under
//! the `cli` feature, the one progress-bar style the binaries draw events with.
//!
//! A sequential job takes `&mut dyn FnMut(Event)`; a job whose units finish on several
//! threads takes `&(dyn Fn(Event) + Sync)` and counts them with a [`Counter`]. Reports that
//! carry results (an inversion's step losses, a training step's metrics) are their own types.

use std::sync::atomic::{AtomicU64, Ordering};

/// `done` of `total` units of `task` ("rendering: model", "generating images").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Event<'a> {
    pub task: &'a str,
    pub done: u64,
    pub total: u64,
}

impl<'a> Event<'a> {
    pub fn new(task: &'a str, done: u64, total: u64) -> Self {
        Event { task, done, total }
    }
}

/// Counts the units of a job that several threads share: each [`Counter::tick`] reports
/// the running count, in whatever order the threads finish.
pub struct Counter<'a> {
    task: &'a str,
    total: u64,
    done: AtomicU64,
    report: &'a (dyn Fn(Event) + Sync),
}

impl<'a> Counter<'a> {
    pub fn new(task: &'a str, total: u64, report: &'a (dyn Fn(Event) + Sync)) -> Self {
        Counter { task, total, done: AtomicU64::new(0), report }
    }

    /// One more unit done.
    pub fn tick(&self) {
        let done = self.done.fetch_add(1, Ordering::Relaxed) + 1;
        (self.report)(Event::new(self.task, done, self.total));
    }
}

#[cfg(feature = "cli")]
pub use bar::{bar, follow, set_quiet, without_quiet};

#[cfg(feature = "cli")]
mod bar {
    use super::Event;
    use indicatif::{ProgressBar, ProgressStyle};
    use std::sync::atomic::{AtomicBool, Ordering};

    /// Every binary's `--quiet`, set once from its command line, so that no subcommand and
    /// no library job can draw a bar the user turned off.
    static QUIET: AtomicBool = AtomicBool::new(false);

    /// Hides every bar made from now on (`--quiet`).
    pub fn set_quiet(quiet: bool) {
        QUIET.store(quiet, Ordering::Relaxed);
    }

    /// A bar of `total` `unit`s: its prefix names the task, its message (set by the caller:
    /// a loss, a step's numbers) comes last. Hidden with `hidden` (a rank that does not
    /// report) or after [`set_quiet`].
    pub fn bar(total: u64, unit: &str, hidden: bool) -> ProgressBar {
        let b = if hidden || QUIET.load(Ordering::Relaxed) { ProgressBar::hidden() } else { ProgressBar::new(total) };
        let template =
            format!("{{prefix}} [{{bar:30}}] {{pos}}/{{len}} {unit} | {{elapsed}} elapsed, eta {{eta}} {{msg}}");
        b.set_style(ProgressStyle::with_template(&template).expect("a valid template").progress_chars("=> "));
        b
    }

    /// The commands of a binary's command line, itself included, that do not take `--quiet`,
    /// each as its words ("gdrf-train eval train-probe"): every binary's test that its
    /// `--quiet` reaches every subcommand, present and future.
    pub fn without_quiet(cmd: &mut clap::Command) -> Vec<String> {
        fn walk(cmd: &clap::Command, path: &str, out: &mut Vec<String>) {
            if !cmd.get_arguments().any(|a| a.get_long() == Some("quiet")) {
                out.push(path.to_string());
            }
            for sub in cmd.get_subcommands().filter(|s| s.get_name() != "help") {
                walk(sub, &format!("{path} {}", sub.get_name()), out);
            }
        }
        cmd.build();
        let mut out = Vec::new();
        walk(cmd, cmd.get_name(), &mut out);
        out
    }

    /// Shows `e` on `b`: the task as the prefix, `done` of `total`.
    pub fn follow(b: &ProgressBar, e: Event) {
        if b.prefix() != e.task {
            b.set_prefix(e.task.to_string());
        }
        b.set_length(e.total);
        b.set_position(e.done);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn a_counter_reports_every_unit_once_from_any_thread() {
        let seen = Mutex::new(Vec::new());
        let report = |e: Event| seen.lock().unwrap().push((e.task.to_string(), e.done, e.total));
        let c = Counter::new("images", 40, &report);
        std::thread::scope(|s| {
            for _ in 0..4 {
                s.spawn(|| (0..10).for_each(|_| c.tick()));
            }
        });
        let mut done: Vec<u64> = seen.lock().unwrap().iter().map(|e| e.1).collect();
        done.sort();
        assert_eq!(done, (1..=40).collect::<Vec<_>>());
        assert!(seen.lock().unwrap().iter().all(|e| e.0 == "images" && e.2 == 40));
    }
}
