//! The picture of a recorded localization run (`kfmap plot --bag`): what RViz shows of a
//! localizer, drawn from a bag of its outputs. The map cloud it published (latched) from
//! above, coloured by height on a dark ground; every pose as an arrow coloured by its
//! health (from the diagnostics of the same stamp) with its 3-sigma x-y covariance
//! ellipse; scans that got no pose (lost, no server, a bad cloud) as crosses; under it,
//! the pose's horizontal uncertainty over time.

use std::collections::HashMap;
use std::path::Path;

use anyhow::Context;
use kfmap_bag::msg::{
    DiagnosticStatusMessage, decode_diagnostic_array, decode_point_cloud2,
    decode_pose_with_covariance,
};
use kfmap_bag::{Bag, Topic};
use nalgebra::{Matrix2, Quaternion, UnitQuaternion, Vector3};
use plotters::coord::Shift;
use plotters::prelude::*;

use super::draw::{
    DEGRADED_ORANGE, Figure, GREY, LOST_RED, Panels, Sizes, Symbol, draw_error, draw_height_points,
    grouped, height_colour, padded_bounds, quantile, time_chart, top_down_chart,
};

/// kfmap-ros2's topics, the defaults of `--pose-topic`, `--map-cloud-topic` and
/// `--diagnostics-topic`.
pub(super) const DEFAULT_POSE_TOPIC: &str = "/kfmap/pose";
pub(super) const DEFAULT_MAP_CLOUD_TOPIC: &str = "/kfmap/map_cloud";
pub(super) const DEFAULT_DIAGNOSTICS_TOPIC: &str = "/diagnostics";
/// Covariance ellipses are drawn at this many standard deviations.
const ELLIPSE_SIGMAS: f64 = 3.0;
/// RViz's default background.
const GROUND: RGBColor = RGBColor(48, 48, 48);
/// A tracked pose's arrow.
const OK_CYAN: RGBColor = RGBColor(0, 200, 255);
/// The path joining the poses.
const PATH_GREEN: RGBColor = RGBColor(25, 255, 0);
/// The view spans these quantiles of the map cloud's x and y (and every pose).
const VIEW_QUANTILES: (f64, f64) = (0.005, 0.995);
/// Height colours span these quantiles of the drawn points' z.
const HEIGHT_QUANTILES: (f64, f64) = (0.02, 0.98);

/// Which topics of the bag to read; `None` takes kfmap-ros2's topic when the bag has
/// it and leaves the layer out when not.
#[derive(Debug, Clone, Default)]
pub struct RunTopics {
    pub pose: Option<String>,
    pub map_cloud: Option<String>,
    pub diagnostics: Option<String>,
}

/// What the picture shows, for the one-line report.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSummary {
    /// Poses on the pose topic.
    pub poses: usize,
    /// Of them, said `ok` / `degraded` by the diagnostics of their stamp.
    pub ok: usize,
    pub degraded: usize,
    /// Poses with no diagnostics of their stamp (or none recorded).
    pub unrated: usize,
    /// Diagnostics of stamps with no pose: lost scans, no server, bad clouds.
    pub without_pose: usize,
    /// Points of the map cloud (0 when the bag has none).
    pub map_points: usize,
    /// Horizontal standard deviation of the poses (the x-y covariance's major axis),
    /// metres: median and largest.
    pub sigma_m: (f64, f64),
    /// Median cloud -> pose latency the diagnostics report (`latency_ms`), ms.
    pub latency_ms_p50: Option<f64>,
}

/// How a diagnostic rated a scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Health {
    Ok,
    Degraded,
    /// No pose: lost, or a warning or error (no server, a bad cloud).
    NoPose,
}

struct PoseMark {
    /// Seconds since the first pose.
    t: f64,
    x: f64,
    y: f64,
    /// Unit heading of the body x axis in the x-y plane (`None`: pointing up or down).
    heading: Option<(f64, f64)>,
    /// The x-y covariance (m^2).
    xy_covariance: Matrix2<f64>,
    health: Option<Health>,
}

impl PoseMark {
    /// The largest horizontal standard deviation, metres.
    fn sigma(&self) -> f64 {
        self.xy_covariance
            .symmetric_eigenvalues()
            .max()
            .max(0.0)
            .sqrt()
    }
}

pub(super) struct RunFigure {
    title: String,
    stats: String,
    /// Map-cloud points (x, y, z), sorted by z (the highest drawn last).
    points: Vec<[f64; 3]>,
    height_range: (f64, f64),
    poses: Vec<PoseMark>,
    /// Scans without a pose: (seconds since the first pose, x, y of the last pose).
    no_pose: Vec<(f64, f64, f64)>,
    bounds: ((f64, f64), (f64, f64)),
    summary: RunSummary,
}

/// The topic `wanted` (or kfmap-ros2's `default` when not given): an error when
/// given and absent or mistyped, `None` when defaulted and absent.
fn optional_topic<'a>(
    bag: &'a Bag,
    wanted: Option<&str>,
    default: &str,
    typed: fn(&'a Bag, &str) -> Result<&'a Topic, kfmap_bag::BagError>,
) -> anyhow::Result<Option<&'a Topic>> {
    match wanted {
        Some(name) => Ok(Some(typed(bag, name)?)),
        None if bag.topics().iter().any(|t| t.name == default) => Ok(Some(typed(bag, default)?)),
        None => Ok(None),
    }
}

fn stamp_key(sec: i64, nanosec: u32) -> i64 {
    sec * 1_000_000_000 + i64::from(nanosec)
}

/// The health one diagnostic status gives a scan: kfmap-ros2's `status` value when
/// present, else the level (OK with a pose; a warning or error means none).
fn health_of(status: &DiagnosticStatusMessage) -> Health {
    match status.value("status") {
        Some("ok") => Health::Ok,
        Some("degraded") => Health::Degraded,
        Some(_) => Health::NoPose,
        None if status.level == 0 => Health::Ok,
        None => Health::NoPose,
    }
}

impl RunFigure {
    pub(super) fn summary(&self) -> &RunSummary {
        &self.summary
    }

    /// Reads the bag: the poses, the diagnostics by stamp, the last map cloud.
    pub(super) fn load(
        bag_path: &Path,
        topics: &RunTopics,
        max_points: usize,
    ) -> anyhow::Result<Self> {
        let bag = Bag::open(bag_path)?;
        let pose_topic =
            bag.pose_with_covariance_topic(topics.pose.as_deref().unwrap_or(DEFAULT_POSE_TOPIC))?;
        let map_topic = optional_topic(
            &bag,
            topics.map_cloud.as_deref(),
            DEFAULT_MAP_CLOUD_TOPIC,
            Bag::point_cloud_topic,
        )?;
        let diagnostics_topic = optional_topic(
            &bag,
            topics.diagnostics.as_deref(),
            DEFAULT_DIAGNOSTICS_TOPIC,
            Bag::diagnostics_topic,
        )?;

        let mut poses = Vec::new();
        let mut frame = String::new();
        for (k, message) in bag.messages(pose_topic)?.enumerate() {
            let message = message?;
            let pose = decode_pose_with_covariance(&message.data, pose_topic.encoding)
                .with_context(|| format!("{} message {k}", pose_topic.name))?;
            frame.clone_from(&pose.frame_id);
            poses.push(pose);
        }
        anyhow::ensure!(
            !poses.is_empty(),
            "{}: no message on {}",
            bag_path.display(),
            pose_topic.name
        );
        poses.sort_by_key(|p| stamp_key(p.stamp.sec, p.stamp.nanosec));
        let t0 = poses[0].stamp.seconds();

        // Diagnostics by stamp: the first status of each array rates its scan.
        let mut rated: HashMap<i64, (Health, f64)> = HashMap::new();
        let mut latencies = Vec::new();
        if let Some(topic) = diagnostics_topic {
            for (k, message) in bag.messages(topic)?.enumerate() {
                let message = message?;
                let array = decode_diagnostic_array(&message.data, topic.encoding)
                    .with_context(|| format!("{} message {k}", topic.name))?;
                let Some(status) = array.status.first() else {
                    continue;
                };
                if let Some(ms) = status
                    .value("latency_ms")
                    .and_then(|v| v.parse::<f64>().ok())
                {
                    latencies.push(ms);
                }
                rated.insert(
                    stamp_key(array.stamp.sec, array.stamp.nanosec),
                    (health_of(status), array.stamp.seconds() - t0),
                );
            }
        }

        let marks: Vec<PoseMark> = poses
            .iter()
            .map(|p| {
                let [qx, qy, qz, qw] = p.orientation;
                let q = UnitQuaternion::from_quaternion(Quaternion::new(qw, qx, qy, qz));
                let axis = q * Vector3::x();
                let norm = axis.xy().norm();
                let c = &p.covariance;
                PoseMark {
                    t: p.stamp.seconds() - t0,
                    x: p.position[0],
                    y: p.position[1],
                    heading: (norm > 0.2).then(|| (axis.x / norm, axis.y / norm)),
                    xy_covariance: Matrix2::new(c[0], c[1], c[6], c[7]),
                    health: rated
                        .get(&stamp_key(p.stamp.sec, p.stamp.nanosec))
                        .map(|(h, _)| *h),
                }
            })
            .collect();
        let pose_stamps: std::collections::HashSet<i64> = poses
            .iter()
            .map(|p| stamp_key(p.stamp.sec, p.stamp.nanosec))
            .collect();
        // A scan with diagnostics but no pose is marked where the last pose before it was.
        let mut no_pose: Vec<(f64, f64, f64)> = rated
            .iter()
            .filter(|(stamp, _)| !pose_stamps.contains(stamp))
            .map(|(_, (_, t))| {
                let before = marks.iter().rev().find(|m| m.t <= *t).unwrap_or(&marks[0]);
                (*t, before.x, before.y)
            })
            .collect();
        no_pose.sort_by(|a, b| a.0.total_cmp(&b.0));

        // The map cloud: the last one published (latched, usually one).
        let mut points: Vec<[f64; 3]> = Vec::new();
        let mut map_points = 0;
        let mut map_note = String::from("no map cloud in the bag");
        if let Some(topic) = map_topic {
            let last = bag.messages(topic)?.last().transpose()?;
            if let Some(message) = last {
                let cloud = decode_point_cloud2(&message.data, topic.encoding)
                    .and_then(|c| c.to_cloud().map(|cloud| (c.frame_id.clone(), cloud)))
                    .with_context(|| format!("{}: the last map cloud", topic.name))?;
                let (cloud_frame, cloud) = cloud;
                map_points = cloud.points.len();
                let step = map_points.div_ceil(max_points.max(1)).max(1);
                points = cloud
                    .points
                    .iter()
                    .step_by(step)
                    .filter(|p| p.iter().all(|v| v.is_finite()))
                    .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
                    .collect();
                map_note = format!("map cloud {} points", grouped(map_points as u64));
                if cloud_frame != frame {
                    map_note += &format!(" (frame {cloud_frame}, poses in {frame})");
                }
            }
        }
        points.sort_by(|a, b| a[2].total_cmp(&b[2]));
        let heights: Vec<f64> = points.iter().map(|p| p[2]).collect();
        let height_range = match (
            quantile(&heights, HEIGHT_QUANTILES.0),
            quantile(&heights, HEIGHT_QUANTILES.1),
        ) {
            (Some(lo), Some(hi)) if hi > lo => (lo, hi),
            (Some(lo), _) => (lo - 0.5, lo + 0.5),
            _ => (0.0, 1.0),
        };
        let mut xs: Vec<f64> = points.iter().map(|p| p[0]).collect();
        let mut ys: Vec<f64> = points.iter().map(|p| p[1]).collect();
        xs.sort_by(f64::total_cmp);
        ys.sort_by(f64::total_cmp);
        let corners = [
            (
                quantile(&xs, VIEW_QUANTILES.0),
                quantile(&ys, VIEW_QUANTILES.0),
            ),
            (
                quantile(&xs, VIEW_QUANTILES.1),
                quantile(&ys, VIEW_QUANTILES.1),
            ),
        ];
        let bounds = padded_bounds(
            marks
                .iter()
                .map(|m| (m.x, m.y))
                .chain(corners.iter().filter_map(|(x, y)| Some(((*x)?, (*y)?)))),
            2.0,
        );

        let mut sigmas: Vec<f64> = marks.iter().map(PoseMark::sigma).collect();
        sigmas.sort_by(f64::total_cmp);
        latencies.sort_by(f64::total_cmp);
        let count = |h: Health| marks.iter().filter(|m| m.health == Some(h)).count();
        let summary = RunSummary {
            poses: marks.len(),
            ok: count(Health::Ok),
            degraded: count(Health::Degraded),
            unrated: marks.iter().filter(|m| m.health.is_none()).count(),
            without_pose: no_pose.len(),
            map_points,
            sigma_m: (
                quantile(&sigmas, 0.5).unwrap_or(0.0),
                sigmas.last().copied().unwrap_or(0.0),
            ),
            latency_ms_p50: quantile(&latencies, 0.5),
        };
        let latency = summary
            .latency_ms_p50
            .map_or(String::new(), |l| format!(", cloud -> pose p50 {l:.1} ms"));
        let stats = format!(
            "{} poses in {frame} over {:.1} s ({} ok, {} degraded), {} scans without a pose; \
             horizontal sigma median {:.1} cm, max {:.1} cm{latency}; {map_note}",
            summary.poses,
            marks.last().map_or(0.0, |m| m.t),
            summary.ok,
            summary.degraded,
            summary.without_pose,
            100.0 * summary.sigma_m.0,
            100.0 * summary.sigma_m.1,
        );
        let name = bag_path.file_name().map_or_else(
            || bag_path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        Ok(Self {
            title: format!("localization run: {name} ({})", pose_topic.name),
            stats,
            points,
            height_range,
            poses: marks,
            no_pose,
            bounds,
            summary,
        })
    }

    fn colour_of(health: Option<Health>) -> RGBColor {
        match health {
            Some(Health::Ok) => OK_CYAN,
            Some(Health::Degraded) => DEGRADED_ORANGE,
            Some(Health::NoPose) => LOST_RED,
            None => GREY,
        }
    }

    fn legend_entries(&self) -> Vec<(Symbol, String)> {
        let s = &self.summary;
        let mut entries = vec![
            (Symbol::Arrow(OK_CYAN), format!("pose, ok ({})", s.ok)),
            (
                Symbol::Arrow(DEGRADED_ORANGE),
                format!("pose, degraded ({})", s.degraded),
            ),
        ];
        if s.unrated > 0 {
            entries.push((
                Symbol::Arrow(GREY),
                format!("pose, no diagnostics ({})", s.unrated),
            ));
        }
        entries.push((
            Symbol::Cross(LOST_RED),
            format!("no pose: lost, no server or bad cloud ({})", s.without_pose),
        ));
        entries.push((Symbol::Line(PATH_GREEN, 1.0, 2), "path".to_string()));
        entries.push((
            Symbol::Ring(RGBColor(255, 0, 255)),
            format!("{ELLIPSE_SIGMAS:.0}-sigma x-y covariance (true scale)"),
        ));
        entries
    }

    /// The view from above: ground, grid, map cloud, path, ellipses, arrows, crosses.
    /// Returns the plotting area's pixel rows, for the colour bar beside it.
    fn draw_top_view<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        sizes: &Sizes,
    ) -> anyhow::Result<std::ops::Range<i32>> {
        let (xr, yr) = self.bounds;
        let (mut chart, mpp) = top_down_chart(area, xr, yr, sizes)?;
        let (x, y) = (chart.x_range(), chart.y_range());
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(x.start, y.start), (x.end, y.end)],
                GROUND.filled(),
            )))
            .map_err(draw_error)?;
        // RViz's grid: cells of a round size, about 10 across the view.
        let cell = nice_step((x.end - x.start) / 10.0);
        let lines = |lo: f64, hi: f64| {
            let first = (lo / cell).ceil() as i64;
            let last = (hi / cell).floor() as i64;
            (first..=last).map(move |i| i as f64 * cell)
        };
        let grid = RGBColor(110, 110, 110).stroke_width(1);
        chart
            .draw_series(
                lines(x.start, x.end)
                    .map(|gx| PathElement::new(vec![(gx, y.start), (gx, y.end)], grid))
                    .chain(
                        lines(y.start, y.end)
                            .map(|gy| PathElement::new(vec![(x.start, gy), (x.end, gy)], grid)),
                    ),
            )
            .map_err(draw_error)?;
        draw_height_points(&mut chart, &self.points, self.height_range)?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                self.poses.iter().map(|m| (m.x, m.y)).collect::<Vec<_>>(),
                PATH_GREEN.stroke_width(2),
            )))
            .map_err(draw_error)?;
        chart
            .draw_series(self.poses.iter().filter_map(|m| {
                ellipse(m.xy_covariance, ELLIPSE_SIGMAS)
                    .map(|pts| {
                        pts.into_iter()
                            .map(|(dx, dy)| (m.x + dx, m.y + dy))
                            .collect::<Vec<_>>()
                    })
                    .map(|pts| PathElement::new(pts, RGBColor(255, 0, 255).stroke_width(2)))
            }))
            .map_err(draw_error)?;
        // Arrows as long as the median step between poses (at least 14 pixels).
        let mut steps: Vec<f64> = self
            .poses
            .windows(2)
            .map(|w| (w[1].x - w[0].x).hypot(w[1].y - w[0].y) / mpp)
            .collect();
        steps.sort_by(f64::total_cmp);
        let max_px = (1.6 * sizes.text).max(16.0);
        let len = quantile(&steps, 0.5).map_or(max_px, |m| (1.2 * m).clamp(14.0, max_px)) * mpp;
        for m in &self.poses {
            let colour = Self::colour_of(m.health);
            let Some((dx, dy)) = m.heading else {
                chart
                    .draw_series(std::iter::once(Circle::new((m.x, m.y), 3, colour.filled())))
                    .map_err(draw_error)?;
                continue;
            };
            let tip = (m.x + dx * len, m.y + dy * len);
            let head = 0.4 * len;
            let base = (tip.0 - dx * head, tip.1 - dy * head);
            let (nx, ny) = (-dy * 0.45 * head, dx * 0.45 * head);
            let corners = vec![tip, (base.0 + nx, base.1 + ny), (base.0 - nx, base.1 - ny)];
            chart
                .draw_series([
                    PathElement::new(vec![(m.x, m.y), base], colour.stroke_width(2)).into_dyn(),
                    Polygon::new(corners, colour.filled()).into_dyn(),
                ])
                .map_err(draw_error)?;
        }
        let r = (0.5 * sizes.text) as i32;
        chart
            .draw_series(
                self.no_pose
                    .iter()
                    .map(|&(_, x, y)| Cross::new((x, y), r, LOST_RED.stroke_width(3))),
            )
            .map_err(draw_error)?;
        Ok(chart.plotting_area().get_pixel_range().1)
    }

    /// The horizontal sigma of every pose over time, coloured by health; scans without
    /// a pose as crosses on the time axis.
    fn draw_sigma_over_time<DB: DrawingBackend>(
        &self,
        area: &DrawingArea<DB, Shift>,
        bar_w: u32,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let t_end = self
            .poses
            .iter()
            .map(|m| m.t)
            .chain(self.no_pose.iter().map(|n| n.0))
            .fold(0.0f64, f64::max)
            .max(1e-3);
        let t_start = self.no_pose.iter().map(|n| n.0).fold(0.0f64, f64::min);
        let top = self
            .poses
            .iter()
            .map(|m| 100.0 * m.sigma())
            .fold(0.0f64, f64::max)
            .max(0.1)
            * 1.1;
        let mut chart = time_chart(
            area,
            bar_w,
            (t_start, t_end),
            top,
            ["time since the first pose (s)", "horizontal sigma (cm)"],
            sizes,
        )?;
        chart
            .draw_series(std::iter::once(PathElement::new(
                self.poses
                    .iter()
                    .map(|m| (m.t, 100.0 * m.sigma()))
                    .collect::<Vec<_>>(),
                RGBColor(90, 90, 90).stroke_width(1),
            )))
            .map_err(draw_error)?;
        let r = (0.2 * sizes.text).max(2.0) as u32;
        chart
            .draw_series(self.poses.iter().map(|m| {
                Circle::new(
                    (m.t, 100.0 * m.sigma()),
                    r,
                    Self::colour_of(m.health).filled(),
                )
            }))
            .map_err(draw_error)?;
        let cross = (0.45 * sizes.text) as i32;
        chart
            .draw_series(
                self.no_pose
                    .iter()
                    .map(|n| Cross::new((n.0, 0.0), cross, LOST_RED.stroke_width(3))),
            )
            .map_err(draw_error)?;
        Ok(())
    }
}

/// A round grid step (1, 2 or 5 times a power of ten) near `raw` metres.
fn nice_step(raw: f64) -> f64 {
    let raw = raw.max(1e-3);
    let power = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * power)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * power)
}

/// The `sigmas`-sigma ellipse of a 2x2 covariance, as offsets from its centre; `None`
/// when the covariance is not positive semi-definite or not finite.
fn ellipse(covariance: Matrix2<f64>, sigmas: f64) -> Option<Vec<(f64, f64)>> {
    if !covariance.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eigen = covariance.symmetric_eigen();
    if eigen.eigenvalues.min() < 0.0 {
        return None;
    }
    let (a, b) = (
        sigmas * eigen.eigenvalues[0].sqrt(),
        sigmas * eigen.eigenvalues[1].sqrt(),
    );
    let (u, v) = (eigen.eigenvectors.column(0), eigen.eigenvectors.column(1));
    Some(
        (0..=48)
            .map(|k| {
                let angle = std::f64::consts::TAU * k as f64 / 48.0;
                let (c, s) = (a * angle.cos(), b * angle.sin());
                (c * u[0] + s * v[0], c * u[1] + s * v[1])
            })
            .collect(),
    )
}

impl Figure for RunFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> anyhow::Result<()> {
        let entries = self.legend_entries();
        let panels = Panels::of(root, &self.title, &self.stats, &entries, 0.72)?;
        let view_rows = self.draw_top_view(&panels.view, &panels.sizes)?;
        panels.colour_bar(
            view_rows,
            self.height_range,
            height_colour,
            "map cloud height z (m)",
        )?;
        self.draw_sigma_over_time(&panels.bottom, panels.bar_w, &panels.sizes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_ellipse_has_the_axes_of_its_covariance() {
        // Axes 0.3 along (1, 1)/sqrt2 and 0.1 across it, sigma 1.
        let (c, s) = (
            std::f64::consts::FRAC_1_SQRT_2,
            std::f64::consts::FRAC_1_SQRT_2,
        );
        let r = Matrix2::new(c, -s, s, c);
        let covariance = r * Matrix2::new(0.09, 0.0, 0.0, 0.01) * r.transpose();
        let points = ellipse(covariance, 1.0).unwrap();
        let longest = points.iter().map(|p| p.0.hypot(p.1)).fold(0.0, f64::max);
        let shortest = points.iter().map(|p| p.0.hypot(p.1)).fold(1.0, f64::min);
        assert!((longest - 0.3).abs() < 1e-3 && (shortest - 0.1).abs() < 2e-3);
        // Every point on x^T C^-1 x = 1.
        let inverse = covariance.try_inverse().unwrap();
        for (x, y) in points {
            let v = nalgebra::Vector2::new(x, y);
            assert!(((v.transpose() * inverse * v)[0] - 1.0).abs() < 1e-9);
        }
        assert!(ellipse(Matrix2::new(-1.0, 0.0, 0.0, 1.0), 3.0).is_none());
        assert!(ellipse(Matrix2::new(f64::NAN, 0.0, 0.0, 1.0), 3.0).is_none());
    }

    #[test]
    fn grid_steps_are_round() {
        assert_eq!(nice_step(0.7), 1.0);
        assert_eq!(nice_step(1.5), 2.0);
        assert_eq!(nice_step(3.0), 5.0);
        assert_eq!(nice_step(7.0), 10.0);
        assert_eq!(nice_step(42.0), 50.0);
    }
}
