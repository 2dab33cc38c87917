//! The trajectory picture: an estimate against its reference, coloured by position
//! error, with the scans a localization run lost or degraded marked.

use std::path::Path;

use anyhow::Context;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::io::read_trajectory;
use kfmap_geometry::trajectory_error::rigid_alignment;
use plotters::coord::Shift;
use plotters::prelude::*;

use super::TrajectoryPlotInputs;
use super::draw::{
    DEGRADED_ORANGE, Figure, GREY, LOST_RED, Panels, Sizes, Symbol, draw_error, ms_label,
    padded_bounds, quantile, time_chart, top_down_chart, viridis,
};

/// Default largest stamp difference between an estimated pose and its reference, s.
pub const DEFAULT_MAX_DT: f64 = 0.005;
/// Error colours saturate at this quantile of the errors.
const ERROR_QUANTILE: f64 = 0.98;

/// What the picture shows, for the one-line report.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectorySummary {
    /// Poses of the estimate.
    pub estimate_poses: usize,
    /// Of them, with a reference pose within the stamp tolerance.
    pub matched: usize,
    /// Root mean square of the position errors, metres.
    pub rmse: f64,
    /// Largest position error, metres.
    pub max: f64,
    /// Scans of the log (lines with an `index`), when one was given.
    pub logged_scans: Option<usize>,
    /// Logged scans lost or failed.
    pub lost: usize,
    /// Logged scans degraded.
    pub degraded: usize,
    /// With `--align`: `T_reference_estimate`, applied to the estimate.
    pub alignment: Option<Pose>,
}

/// How to compare the estimate with the reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryOptions {
    /// Largest stamp difference between an estimated pose and its reference, s.
    pub max_dt: f64,
    /// Move the estimate rigidly onto the reference (no scale) first.
    pub align: bool,
}

impl Default for TrajectoryOptions {
    fn default() -> Self {
        Self {
            max_dt: DEFAULT_MAX_DT,
            align: false,
        }
    }
}

/// A pose of the estimate with its reference: seconds from the first estimated stamp,
/// estimated position, error.
struct Matched {
    t: f64,
    x: f64,
    y: f64,
    error: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum MarkKind {
    LostOrFailed,
    Degraded,
}

/// A logged scan that was not `ok`.
struct Mark {
    t: f64,
    x: f64,
    y: f64,
    /// Its position error: the matched estimate's at its stamp (`None`: no match).
    error: Option<f64>,
    kind: MarkKind,
}

pub(super) struct TrajectoryFigure {
    title: String,
    stats: String,
    reference: Vec<(f64, f64)>,
    matched: Vec<Matched>,
    marks: Vec<Mark>,
    error_range: (f64, f64),
    has_log: bool,
    summary: TrajectorySummary,
}

/// Stamped poses of a TUM file, in time order.
fn read_stamped(path: &Path, what: &str) -> anyhow::Result<Vec<(f64, Pose)>> {
    let traj = read_trajectory(path).with_context(|| format!("cannot read the {what}"))?;
    let stamps = traj.stamps.ok_or_else(|| {
        anyhow::anyhow!(
            "{}: the {what} has no timestamps (KITTI format); poses are matched by time, \
             so pass a TUM file (t x y z qx qy qz qw)",
            path.display()
        )
    })?;
    anyhow::ensure!(
        !traj.poses.is_empty(),
        "{}: the {what} is empty (no poses)",
        path.display()
    );
    let mut out: Vec<(f64, Pose)> = stamps.into_iter().zip(traj.poses).collect();
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// A length for people: millimetres below 0.1 m, else metres to the millimetre.
fn length_label(metres: f64) -> String {
    if metres < 0.1 {
        format!("{:.1} mm", metres * 1e3)
    } else {
        format!("{metres:.3} m")
    }
}

/// Index of the entry of `sorted` (by stamp) nearest to `t`, if within `max_dt`.
fn nearest<T>(sorted: &[(f64, T)], t: f64, max_dt: f64) -> Option<usize> {
    let i = sorted.partition_point(|(s, _)| *s < t);
    [i.checked_sub(1), (i < sorted.len()).then_some(i)]
        .into_iter()
        .flatten()
        .filter(|&j| (sorted[j].0 - t).abs() <= max_dt)
        .min_by(|&a, &b| (sorted[a].0 - t).abs().total_cmp(&(sorted[b].0 - t).abs()))
}

/// One scan of a `kfmap localize --json-lines` log.
struct LoggedScan {
    t: f64,
    status: String,
    position: Option<[f64; 3]>,
}

/// The scans of a `--json-lines` log; lines without `index` (the summary) are skipped.
fn read_scan_log(path: &Path) -> anyhow::Result<Vec<LoggedScan>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the scan log {}", path.display()))?;
    let mut scans = Vec::new();
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let value: serde_json::Value = serde_json::from_str(line).with_context(|| {
            format!(
                "{} line {}: not a JSON object (expected `kfmap localize --json-lines` output)",
                path.display(),
                k + 1
            )
        })?;
        if value.get("index").is_none() {
            continue;
        }
        let field = |name: &str| {
            anyhow::anyhow!(
                "{} line {}: a scan without a valid \"{name}\"",
                path.display(),
                k + 1
            )
        };
        let t = value["t"].as_f64().ok_or_else(|| field("t"))?;
        let status = value["status"].as_str().ok_or_else(|| field("status"))?;
        let position = value["pose"].as_array().and_then(|p| {
            let x = p.first()?.as_f64()?;
            let y = p.get(1)?.as_f64()?;
            let z = p.get(2)?.as_f64()?;
            Some([x, y, z])
        });
        scans.push(LoggedScan {
            t,
            status: status.to_string(),
            position,
        });
    }
    Ok(scans)
}

/// Pairs (estimate index, reference index): each estimated pose with the reference
/// pose nearest in time, within `max_dt` seconds.
fn pairs_by_stamp(
    estimate: &[(f64, Pose)],
    reference: &[(f64, Pose)],
    max_dt: f64,
) -> Vec<(usize, usize)> {
    estimate
        .iter()
        .enumerate()
        .filter_map(|(i, (t, _))| Some((i, nearest(reference, *t, max_dt)?)))
        .collect()
}

/// Moves `estimate` rigidly onto `reference` (least squares over the positions of
/// `pairs`, no scale); returns `T_reference_estimate`.
fn align_estimate(
    estimate: &mut [(f64, Pose)],
    reference: &[(f64, Pose)],
    pairs: &[(usize, usize)],
) -> anyhow::Result<Pose> {
    anyhow::ensure!(
        pairs.len() >= 3,
        "--align needs at least 3 matched poses, found {}",
        pairs.len()
    );
    let est: Vec<Pose> = pairs.iter().map(|&(i, _)| estimate[i].1).collect();
    let refs: Vec<Pose> = pairs.iter().map(|&(_, j)| reference[j].1).collect();
    let align = rigid_alignment(&est, &refs);
    for (_, pose) in estimate.iter_mut() {
        *pose = align * *pose;
    }
    Ok(align)
}

/// The matched estimated poses with their position errors; an error when none matched.
fn matched_errors(
    estimate: &[(f64, Pose)],
    reference: &[(f64, Pose)],
    pairs: &[(usize, usize)],
    max_dt: f64,
) -> anyhow::Result<Vec<Matched>> {
    let t0 = estimate[0].0;
    let matched: Vec<Matched> = pairs
        .iter()
        .map(|&(i, j)| {
            let (t, p) = &estimate[i];
            let p = p.translation.vector;
            Matched {
                t: t - t0,
                x: p.x,
                y: p.y,
                error: (p - reference[j].1.translation.vector).norm(),
            }
        })
        .collect();
    if matched.is_empty() {
        anyhow::bail!(
            "no estimated pose has a reference pose within {} ms: estimate stamps {:.3}..{:.3} s, \
             reference {:.3}..{:.3} s (are they on the same clock?)",
            ms_label(max_dt),
            estimate[0].0,
            estimate[estimate.len() - 1].0,
            reference[0].0,
            reference[reference.len() - 1].0
        );
    }
    Ok(matched)
}

/// RMSE and maximum of the position errors, and where the colours saturate.
struct ErrorFigures {
    rmse: f64,
    max: f64,
    /// [`ERROR_QUANTILE`] of the errors (at least 1 mm): the colour scale's top.
    top: f64,
}

impl ErrorFigures {
    /// The figures of `matched` (not empty).
    fn of(matched: &[Matched]) -> Self {
        let mut errors: Vec<f64> = matched.iter().map(|m| m.error).collect();
        errors.sort_by(f64::total_cmp);
        let rmse = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
        let max = errors[errors.len() - 1];
        let top = quantile(&errors, ERROR_QUANTILE).unwrap_or(max).max(1e-3);
        Self { rmse, max, top }
    }
}

/// The reference's positions within the estimate's time span (1 s either side).
fn reference_in_span(reference: &[(f64, Pose)], estimate: &[(f64, Pose)]) -> Vec<(f64, f64)> {
    let (first, last) = (estimate[0].0 - 1.0, estimate[estimate.len() - 1].0 + 1.0);
    reference
        .iter()
        .filter(|(t, _)| (first..=last).contains(t))
        .map(|(_, p)| (p.translation.x, p.translation.y))
        .collect()
}

/// The marks of a scan log: its scans within the estimate's span that were not `ok`.
struct LogMarks {
    marks: Vec<Mark>,
    /// Scans of the log within the estimate's span.
    logged: usize,
    /// Of them, lost or failed.
    lost: usize,
    /// Of them, degraded.
    degraded: usize,
}

impl LogMarks {
    /// Reads the `--json-lines` log at `log` and marks its lost, failed and degraded
    /// scans: at their logged position (moved by `alignment`), else the estimate's at
    /// their stamp, with the matched error at their stamp.
    fn read(
        log: &Path,
        estimate: &[(f64, Pose)],
        matched: &[Matched],
        alignment: Option<&Pose>,
        max_dt: f64,
    ) -> anyhow::Result<Self> {
        let t0 = estimate[0].0;
        let scans = logged_scans_in_span(log, estimate, max_dt)?;
        let by_stamp: Vec<(f64, usize)> = {
            let mut v: Vec<(f64, usize)> = matched
                .iter()
                .enumerate()
                .map(|(i, m)| (m.t + t0, i))
                .collect();
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            v
        };
        let estimate_at = |t: f64| {
            nearest(estimate, t, max_dt).map(|j| {
                let v = estimate[j].1.translation.vector;
                [v.x, v.y]
            })
        };
        let mut out = Self {
            marks: Vec::new(),
            logged: scans.len(),
            lost: 0,
            degraded: 0,
        };
        for scan in &scans {
            let kind = match scan.status.as_str() {
                "lost" | "failed" => MarkKind::LostOrFailed,
                "degraded" => MarkKind::Degraded,
                _ => continue,
            };
            match kind {
                MarkKind::LostOrFailed => out.lost += 1,
                MarkKind::Degraded => out.degraded += 1,
            }
            // The logged pose is in the estimate's frame: aligned with it.
            let logged = scan.position.map(|p| match alignment {
                Some(a) => {
                    let q = a * nalgebra::Point3::new(p[0], p[1], p[2]);
                    [q.x, q.y]
                }
                None => [p[0], p[1]],
            });
            let Some([x, y]) = logged.or_else(|| estimate_at(scan.t)) else {
                continue;
            };
            let error = nearest(&by_stamp, scan.t, max_dt).map(|j| matched[by_stamp[j].1].error);
            out.marks.push(Mark {
                t: scan.t - t0,
                x,
                y,
                error,
                kind,
            });
        }
        Ok(out)
    }
}

/// The scans of the log at `log` stamped within the estimate's span (`max_dt` either
/// side); an error when there is none: a log of another run or clock marks nothing.
fn logged_scans_in_span(
    log: &Path,
    estimate: &[(f64, Pose)],
    max_dt: f64,
) -> anyhow::Result<Vec<LoggedScan>> {
    let all = read_scan_log(log)?;
    let (start, end) = (
        estimate[0].0 - max_dt,
        estimate[estimate.len() - 1].0 + max_dt,
    );
    let scans: Vec<_> = all
        .into_iter()
        .filter(|s| (start..=end).contains(&s.t))
        .collect();
    anyhow::ensure!(
        !scans.is_empty(),
        "{}: no logged scan is stamped within the estimate's {start:.3}..{end:.3} s (a log of another run?)",
        log.display()
    );
    Ok(scans)
}

/// "ESTIMATE against REFERENCE", by file name.
fn default_title(inputs: &TrajectoryPlotInputs) -> String {
    let name = |p: &Path| {
        p.file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| p.display().to_string())
    };
    format!(
        "{} against {}",
        name(inputs.estimate),
        name(inputs.reference)
    )
}

/// The line under the title: poses matched, the errors, the alignment and the log's
/// counts.
fn stats_line(
    matched: &[Matched],
    estimate_poses: usize,
    max_dt: f64,
    errors: &ErrorFigures,
    alignment: Option<&Pose>,
    marks: Option<&LogMarks>,
) -> String {
    let mut stats = format!(
        "{} of {} poses matched within {} ms  ·  position error RMSE {}, max {}",
        matched.len(),
        estimate_poses,
        ms_label(max_dt),
        length_label(errors.rmse),
        length_label(errors.max)
    );
    if let Some(a) = alignment {
        stats.push_str(&format!(
            "  ·  aligned: rotated {:.2}°, moved {:.3} m",
            a.rotation.angle().to_degrees(),
            a.translation.vector.norm()
        ));
    }
    if let Some(m) = marks {
        stats.push_str(&format!(
            "  ·  {} lost/failed, {} degraded of {} scans",
            m.lost, m.degraded, m.logged
        ));
    }
    stats
}

impl TrajectoryFigure {
    pub(super) fn summary(&self) -> &TrajectorySummary {
        &self.summary
    }

    /// Reads and matches the inputs: each estimated pose to the reference pose nearest
    /// in time, within `max_dt` seconds.
    pub(super) fn load(
        inputs: &TrajectoryPlotInputs,
        options: &TrajectoryOptions,
    ) -> anyhow::Result<Self> {
        let max_dt = options.max_dt;
        anyhow::ensure!(
            max_dt.is_finite() && max_dt >= 0.0,
            "--max-dt-ms must be >= 0, got {}",
            max_dt * 1e3
        );
        let reference = read_stamped(inputs.reference, "reference trajectory")?;
        let mut estimate = read_stamped(inputs.estimate, "estimated trajectory")?;
        let pairs = pairs_by_stamp(&estimate, &reference, max_dt);
        // --align: the estimate moved rigidly onto the reference (least squares over
        // the matched positions, no scale) before anything is measured or drawn.
        let alignment = if options.align && !pairs.is_empty() {
            Some(align_estimate(&mut estimate, &reference, &pairs)?)
        } else {
            None
        };
        let matched = matched_errors(&estimate, &reference, &pairs, max_dt)?;
        let errors = ErrorFigures::of(&matched);
        let reference_xy = reference_in_span(&reference, &estimate);
        let marks = match inputs.scan_log {
            Some(log) => Some(LogMarks::read(
                log,
                &estimate,
                &matched,
                alignment.as_ref(),
                max_dt,
            )?),
            None => None,
        };
        let title = inputs
            .title
            .map(str::to_string)
            .unwrap_or_else(|| default_title(inputs));
        let stats = stats_line(
            &matched,
            estimate.len(),
            max_dt,
            &errors,
            alignment.as_ref(),
            marks.as_ref(),
        );
        let (lost, degraded) = marks.as_ref().map_or((0, 0), |m| (m.lost, m.degraded));
        let logged = marks.as_ref().map(|m| m.logged);
        Ok(Self {
            title,
            stats,
            reference: reference_xy,
            error_range: (0.0, errors.top),
            has_log: logged.is_some(),
            summary: TrajectorySummary {
                estimate_poses: estimate.len(),
                matched: matched.len(),
                rmse: errors.rmse,
                max: errors.max,
                logged_scans: logged,
                lost,
                degraded,
                alignment,
            },
            matched,
            marks: marks.map_or_else(Vec::new, |m| m.marks),
        })
    }

    fn legend_entries(&self) -> Vec<(Symbol, String)> {
        let mut entries = vec![
            (Symbol::Line(GREY, 1.0, 3), "reference".to_string()),
            (
                Symbol::Gradient(viridis),
                "estimate, coloured by position error".to_string(),
            ),
            (Symbol::Ring(BLACK), "start".to_string()),
        ];
        if self.has_log {
            entries.push((
                Symbol::Cross(LOST_RED),
                format!("lost or failed scan ({})", self.summary.lost),
            ));
            entries.push((
                Symbol::Triangle(DEGRADED_ORANGE),
                format!("degraded scan ({})", self.summary.degraded),
            ));
        }
        entries
    }

    fn colour(&self, error: f64) -> RGBColor {
        viridis(error / self.error_range.1)
    }

    fn draw_marks<DB: DrawingBackend>(
        &self,
        chart: &mut super::draw::Chart2d<'_, DB>,
        at: impl Fn(&Mark) -> Option<(f64, f64)>,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let r = (0.45 * sizes.text) as i32;
        chart
            .draw_series(
                self.marks
                    .iter()
                    .filter(|m| m.kind == MarkKind::Degraded)
                    .filter_map(&at)
                    .map(|c| TriangleMarker::new(c, r, DEGRADED_ORANGE.filled())),
            )
            .map_err(draw_error)?;
        chart
            .draw_series(
                self.marks
                    .iter()
                    .filter(|m| m.kind == MarkKind::LostOrFailed)
                    .filter_map(&at)
                    .map(|c| Cross::new(c, r, LOST_RED.stroke_width(3))),
            )
            .map_err(draw_error)?;
        Ok(())
    }
}

impl TrajectoryFigure {
    /// Width of the estimate's line and radius of its dots, pixels.
    fn line_width(sizes: &Sizes) -> u32 {
        (0.2 * sizes.text).max(2.0) as u32
    }

    /// The view from above in `area`: the reference in grey, the estimate coloured by
    /// its error, its start ringed, the log's marks. Returns the plotting area's pixel
    /// rows, for the colour bar beside it.
    fn draw_top_view<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        sizes: &Sizes,
    ) -> anyhow::Result<std::ops::Range<i32>> {
        let (xr, yr) = padded_bounds(
            self.reference
                .iter()
                .copied()
                .chain(self.matched.iter().map(|m| (m.x, m.y)))
                .chain(self.marks.iter().map(|m| (m.x, m.y))),
            1.0,
        );
        let (mut chart, _) = top_down_chart(area, xr, yr, sizes)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                self.reference.clone(),
                GREY.stroke_width(3),
            )))
            .map_err(draw_error)?;
        let line_w = Self::line_width(sizes);
        chart
            .draw_series(self.matched.windows(2).map(|w| {
                let c = self.colour(0.5 * (w[0].error + w[1].error));
                PathElement::new(
                    vec![(w[0].x, w[0].y), (w[1].x, w[1].y)],
                    c.stroke_width(line_w),
                )
            }))
            .map_err(draw_error)?;
        chart
            .draw_series(
                self.matched
                    .iter()
                    .map(|m| Circle::new((m.x, m.y), line_w, self.colour(m.error).filled())),
            )
            .map_err(draw_error)?;
        let start = &self.matched[0];
        chart
            .draw_series(std::iter::once(Circle::new(
                (start.x, start.y),
                (0.45 * sizes.text) as u32,
                BLACK.stroke_width(2),
            )))
            .map_err(draw_error)?;
        self.draw_marks(&mut chart, |m| Some((m.x, m.y)), sizes)?;
        Ok(chart.plotting_area().get_pixel_range().1)
    }

    /// The position error over time in `area` (its right margin `bar_w` wide, under the
    /// colour bar), with the log's marks; a mark with no known error sits on the time
    /// axis.
    fn draw_error_over_time<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        bar_w: u32,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let t_end = self
            .matched
            .iter()
            .map(|m| m.t)
            .chain(self.marks.iter().map(|m| m.t))
            .fold(0.0f64, f64::max)
            .max(1e-3);
        let t_start = self.marks.iter().map(|m| m.t).fold(0.0f64, f64::min);
        let e_max = self
            .matched
            .iter()
            .map(|m| m.error)
            .chain(self.marks.iter().filter_map(|m| m.error))
            .fold(0.0f64, f64::max)
            .max(1e-3)
            * 1.08;
        let mut chart = time_chart(
            area,
            bar_w,
            (t_start, t_end),
            e_max,
            [
                "time since the first estimated pose (s)",
                "position error (m)",
            ],
            sizes,
        )?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                self.matched
                    .iter()
                    .map(|m| (m.t, m.error))
                    .collect::<Vec<_>>(),
                RGBColor(90, 90, 90).stroke_width(1),
            )))
            .map_err(draw_error)?;
        let line_w = Self::line_width(sizes);
        chart
            .draw_series(
                self.matched
                    .iter()
                    .map(|m| Circle::new((m.t, m.error), line_w, self.colour(m.error).filled())),
            )
            .map_err(draw_error)?;
        self.draw_marks(&mut chart, |m| Some((m.t, m.error.unwrap_or(0.0))), sizes)?;
        Ok(())
    }
}

impl Figure for TrajectoryFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> anyhow::Result<()> {
        let entries = self.legend_entries();
        let panels = Panels::of(root, &self.title, &self.stats, &entries, 0.66)?;
        // Top: the view from above, its colour bar beside the plotting area; bottom:
        // the error over time.
        let view_rows = self.draw_top_view(&panels.view, &panels.sizes)?;
        panels.colour_bar(view_rows, self.error_range, viridis, "position error (m)")?;
        self.draw_error_over_time(&panels.bottom, panels.bar_w, &panels.sizes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_respects_the_tolerance() {
        let v = [(0.0, ()), (0.1, ()), (0.2, ())];
        assert_eq!(nearest(&v, 0.104, 0.005), Some(1));
        assert_eq!(nearest(&v, 0.096, 0.005), Some(1));
        assert_eq!(nearest(&v, 0.15, 0.005), None);
        assert_eq!(nearest(&v, 0.2049, 0.005), Some(2));
        assert_eq!(nearest(&v, -0.01, 0.005), None);
        assert_eq!(nearest::<()>(&[], 0.0, 1.0), None);
    }
}
