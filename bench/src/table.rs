//! The benchmark table: its rows (each naming its data and threads, with the anchor's
//! figure beside it where one was measured on the same data), the timing of in-process
//! rows, and the table printed as text or JSON.

use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use kfmap_geometry::percentile::percentile;
use serde_json::json;

/// An anchor's figure for the same measurement on the same data and machine.
#[derive(Clone, Copy)]
pub(super) struct Anchor {
    tool: &'static str,
    value: f64,
    script: &'static str,
}

/// The anchor figure `value` of `tool`, measured by `script`.
pub(super) fn anchor(tool: &'static str, value: f64, script: &'static str) -> Option<Anchor> {
    Some(Anchor {
        tool,
        value,
        script,
    })
}

/// One measured figure.
struct Row {
    name: String,
    data: String,
    threads: usize,
    value: f64,
    unit: &'static str,
    anchor: Option<Anchor>,
}

/// How long each in-process timing runs its work before sampling.
const WARM_UP: std::time::Duration = std::time::Duration::from_millis(300);

/// The rows measured so far, and the progress shown while measuring.
pub(super) struct Table {
    rows: Vec<Row>,
    skipped: Vec<String>,
    bar: ProgressBar,
    /// Repetitions per in-process timing (the median is kept).
    reps: usize,
    /// A smoke run (`--quick`): fewer repetitions, smaller generated maps.
    pub quick: bool,
}

impl Table {
    /// An empty table, showing its progress unless the output is JSON.
    pub fn new(quick: bool, json_out: bool) -> anyhow::Result<Self> {
        let bar = if json_out {
            ProgressBar::hidden()
        } else {
            ProgressBar::new_spinner()
        };
        bar.set_style(ProgressStyle::with_template("{spinner} {elapsed} {msg}")?);
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        Ok(Self {
            rows: Vec::new(),
            skipped: Vec::new(),
            bar,
            reps: if quick { 3 } else { 15 },
            quick,
        })
    }

    /// Adds a row without an anchor.
    pub fn push(&mut self, name: &str, data: &str, threads: usize, value: f64, unit: &'static str) {
        self.rows.push(Row {
            name: name.into(),
            data: data.into(),
            threads,
            value,
            unit,
            anchor: None,
        });
    }

    /// Sets the anchor of the last row pushed.
    pub fn anchored(&mut self, anchor: Option<Anchor>) {
        if let Some(row) = self.rows.last_mut() {
            row.anchor = anchor;
        }
    }

    /// Lists a benchmark that could not run, and why.
    pub fn skip(&mut self, why: &str) {
        self.skipped.push(why.into());
    }

    /// Shows what is being measured.
    pub fn stage(&self, what: &str) {
        self.bar.set_message(what.to_string());
        self.bar.tick();
    }

    /// Clears the progress shown: every row is measured.
    pub fn finish(&self) {
        self.bar.finish_and_clear();
    }

    /// Median milliseconds of `reps` runs of `work` on a pool of `threads`, after
    /// [`WARM_UP`] of runs.
    pub fn time_ms<T: Send>(
        &self,
        threads: usize,
        mut work: impl FnMut() -> T + Send,
    ) -> anyhow::Result<f64> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()?;
        // Warm caches, the pool and the cores: after a single run, a new pool's second
        // thread on this VM still ran cold (2-thread rows up to 2x slow, criterion not).
        let warming = Instant::now();
        let warm_up = if self.quick { WARM_UP / 3 } else { WARM_UP };
        while warming.elapsed() < warm_up {
            std::hint::black_box(pool.install(&mut work));
        }
        let mut samples = Vec::with_capacity(self.reps);
        for _ in 0..self.reps {
            let started = Instant::now();
            std::hint::black_box(pool.install(&mut work));
            samples.push(started.elapsed().as_secs_f64() * 1e3);
        }
        samples.sort_by(f64::total_cmp);
        Ok(percentile(&samples, 0.5))
    }

    /// `--json`'s object: {"quick", "cores", "rows": [{name, data, threads, value,
    /// unit, anchor: {tool, value, script} | null}], "skipped": [...]}.
    pub fn json(&self) -> serde_json::Value {
        let rows: Vec<_> = self
            .rows
            .iter()
            .map(|r| {
                json!({
                    "name": r.name.trim(),
                    "data": r.data,
                    "threads": r.threads,
                    "value": r.value,
                    "unit": r.unit,
                    "anchor": r.anchor.map(|a| json!({"tool": a.tool, "value": a.value, "script": a.script})),
                })
            })
            .collect();
        json!({
            "quick": self.quick,
            "cores": std::thread::available_parallelism().map_or(0, |n| n.get()),
            "rows": rows,
            "skipped": self.skipped,
        })
    }

    /// The table as Markdown, then where the anchors' figures come from and what was
    /// skipped.
    pub fn text(&self) -> String {
        let mut out = self.markdown();
        let scripts: std::collections::BTreeSet<&str> = self
            .rows
            .iter()
            .filter_map(|r| r.anchor.map(|a| a.script))
            .collect();
        if !scripts.is_empty() {
            out += &format!(
                "\nAnchor figures: recorded on this project's 2-core machine by {} (see docs/BENCHMARKS.md).\n",
                scripts.into_iter().collect::<Vec<_>>().join(", ")
            );
        }
        if self.quick {
            out +=
                "Quick run: fewer repetitions and a smaller generated map; figures are noisier.\n";
        }
        for s in &self.skipped {
            out += &format!("skipped: {s}\n");
        }
        out
    }

    /// The rows as a Markdown table, the columns padded to their widest cell.
    fn markdown(&self) -> String {
        let header = ["benchmark", "data", "threads", "kfmap", "anchor"];
        let cells: Vec<[String; 5]> = self
            .rows
            .iter()
            .map(|r| {
                [
                    r.name.clone(),
                    r.data.clone(),
                    r.threads.to_string(),
                    figure(r.value, r.unit),
                    r.anchor.map_or(String::new(), |a| {
                        format!("{} {}", a.tool, figure(a.value, r.unit))
                    }),
                ]
            })
            .collect();
        let widths: Vec<usize> = (0..5)
            .map(|c| {
                cells
                    .iter()
                    .map(|r| r[c].chars().count())
                    .chain([header[c].len()])
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let line = |r: [&str; 5]| {
            let mut s = String::from("|");
            for c in 0..5 {
                if c == 2 || c == 3 {
                    s += &format!(" {:>w$} |", r[c], w = widths[c]);
                } else {
                    s += &format!(" {:w$} |", r[c], w = widths[c]);
                }
            }
            s + "\n"
        };
        let mut out = line(header);
        out += &format!(
            "|{}|\n",
            widths
                .iter()
                .enumerate()
                .map(|(c, w)| if c == 2 || c == 3 {
                    format!("{}:", "-".repeat(w + 1))
                } else {
                    "-".repeat(w + 2)
                })
                .collect::<Vec<_>>()
                .join("|")
        );
        for r in &cells {
            out += &line([&r[0], &r[1], &r[2], &r[3], &r[4]]);
        }
        out
    }
}

/// A figure with about three significant digits.
fn figure(value: f64, unit: &str) -> String {
    let digits = match value.abs() {
        v if v >= 100.0 => 0,
        v if v >= 10.0 => 1,
        v if v >= 1.0 => 2,
        _ => 3,
    };
    format!("{value:.digits$} {unit}")
}
