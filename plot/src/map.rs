//! The map picture: a top-down view of a baked map's points coloured by height, its
//! keyframe poses and covisibility edges.

use std::collections::HashMap;
use std::path::Path;

use anyhow::Context;
use kfmap_map::archive::{ArchiveError, OpenOptions, open_map};
use kfmap_map::map::KeyframeMap;
use nalgebra::Vector3;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::MapPlotOptions;
use super::draw::{
    Chart2d, Figure, GREY, REVISIT_MAGENTA, Sizes, Symbol, centred_text, colour_bar, draw_error,
    draw_height_points, grouped, height_colour, legend, legend_height, padded_bounds, plural,
    quantile, top_down_chart,
};

/// Most points drawn in a PNG (every n-th point of the map, n fixed by the total).
pub(super) const MAX_POINTS_PNG: usize = 300_000;
/// Most points drawn in an SVG (one element each).
pub(super) const MAX_POINTS_SVG: usize = 60_000;
/// Covisibility between two keyframes is a revisit (a loop closure, or a later pass)
/// when they are near each other, at most `REVISIT_NEAR` times the median keyframe step
/// or `REVISIT_NEAR_M` metres apart, whichever is more, and the keyframe path between
/// them is longer than `REVISIT_DETOUR` times their distance plus `REVISIT_SLACK_M`
/// metres: the robot drove away and came back.
pub(super) const REVISIT_NEAR: f64 = 3.0;
pub(super) const REVISIT_NEAR_M: f64 = 5.0;
pub(super) const REVISIT_DETOUR: f64 = 2.0;
pub(super) const REVISIT_SLACK_M: f64 = 10.0;
/// Plain covisibility edges drawn: each keyframe's strongest (most shared voxels) few;
/// in an open area every keyframe sees every other one, and all edges would hide the
/// map under a blot.
pub(super) const STRONGEST_PER_KEYFRAME: usize = 3;
/// The view spans these quantiles of the points' x and y (and every keyframe).
const VIEW_QUANTILES: (f64, f64) = (0.005, 0.995);
/// Height colours span these quantiles of the drawn points' z.
const HEIGHT_QUANTILES: (f64, f64) = (0.02, 0.98);

/// What the picture shows, for the one-line report.
#[derive(Debug, Clone, PartialEq)]
pub struct MapSummary {
    pub keyframes: usize,
    pub points: u64,
    pub drawn: usize,
    /// Covisibility edges of the map.
    pub covisibility_edges: usize,
    /// Of them, across a revisit.
    pub revisit_edges: usize,
    /// Edges drawn (when edges are drawn): plain and across a revisit.
    pub drawn_edges: (usize, usize),
    /// Height colour range, metres.
    pub height_range: (f64, f64),
}

struct KeyframeMark {
    x: f64,
    y: f64,
    /// Unit direction of the keyframe's x axis in the xy plane; `None` when the axis
    /// points (nearly) up or down.
    heading: Option<(f64, f64)>,
}

struct Edge {
    a: usize,
    b: usize,
    weight: u32,
    revisit: bool,
}

pub(super) struct MapFigure {
    name: String,
    keyframes: Vec<KeyframeMark>,
    /// Map-frame points, sorted by z (the highest drawn last: the view from above).
    points: Vec<[f64; 3]>,
    /// x and y ranges shown (before the equal-aspect widening).
    bounds: ((f64, f64), (f64, f64)),
    edges: Vec<Edge>,
    edges_shown: bool,
    summary: MapSummary,
}

/// What reading the map's keyframes gave: the sampled points and each keyframe's mark.
struct Sampled {
    /// Points of the map.
    total: u64,
    /// Every n-th point, map frame.
    points: Vec<[f64; 3]>,
    keyframes: Vec<KeyframeMark>,
    /// (timestamp, id, index in `keyframes`) of each keyframe.
    order: Vec<(f64, u64, usize)>,
    /// Index in `keyframes` of each keyframe id.
    index_of: HashMap<u64, usize>,
}

impl Sampled {
    /// Reads every keyframe of `map` (at `path`, for errors): its pose's mark, and every
    /// n-th point (n = ceil(points / max_points), counted across keyframes) moved into
    /// the map frame.
    fn read(map: &KeyframeMap, path: &Path, max_points: usize) -> anyhow::Result<Self> {
        let total: u64 = map.keyframes().map(|k| k.len() as u64).sum();
        let stride = total.div_ceil(max_points.max(1) as u64).max(1) as usize;
        let mut out = Self {
            total,
            points: Vec::with_capacity((total as usize / stride) + 1),
            keyframes: Vec::with_capacity(map.len()),
            order: Vec::with_capacity(map.len()),
            index_of: HashMap::with_capacity(map.len()),
        };
        let mut seen = 0usize;
        for (i, k) in map.keyframes().enumerate() {
            let view = k
                .view()
                .with_context(|| format!("{}: cannot read keyframe {}", path.display(), k.id))?;
            let first = (stride - seen % stride) % stride;
            for p in view.points.iter().skip(first).step_by(stride) {
                let q = kfmap_geometry::geometry::transform_point(&k.pose, p);
                out.points.push([q.x, q.y, q.z]);
            }
            seen += view.points.len();
            let t = k.pose.translation.vector;
            let axis = k.pose.rotation * Vector3::x();
            let norm = axis.x.hypot(axis.y);
            out.keyframes.push(KeyframeMark {
                x: t.x,
                y: t.y,
                heading: (norm > 0.2).then(|| (axis.x / norm, axis.y / norm)),
            });
            out.order.push((k.timestamp, k.id, i));
            out.index_of.insert(k.id, i);
        }
        Ok(out)
    }
}

/// The view: keyframes and the points between the 0.5th and 99.5th percentiles of x
/// and of y (a few spurious far returns must not shrink the map to a dot), padded;
/// points outside are not drawn.
fn view_bounds(points: &[[f64; 3]], keyframes: &[KeyframeMark]) -> ((f64, f64), (f64, f64)) {
    let axis_range = |axis: usize| {
        let mut v: Vec<f64> = points.iter().map(|p| p[axis]).collect();
        v.sort_by(f64::total_cmp);
        quantile(&v, VIEW_QUANTILES.0).zip(quantile(&v, VIEW_QUANTILES.1))
    };
    let corners: Vec<(f64, f64)> = match (axis_range(0), axis_range(1)) {
        (Some(x), Some(y)) => vec![(x.0, y.0), (x.1, y.1)],
        _ => Vec::new(),
    };
    padded_bounds(
        corners
            .into_iter()
            .chain(keyframes.iter().map(|k| (k.x, k.y))),
        1.0,
    )
}

/// The map's covisibility edges between keyframes, each marked whether it is across a
/// revisit: covisible keyframes near each other with a long drive between them (the
/// path driven in time `order`).
fn classified_edges(
    map: &KeyframeMap,
    index_of: &HashMap<u64, usize>,
    keyframes: &[KeyframeMark],
    mut order: Vec<(f64, u64, usize)>,
) -> Vec<Edge> {
    // Path length driven to each keyframe, in time order.
    order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut driven = vec![0.0f64; keyframes.len()];
    let mut total_m = 0.0;
    let mut steps = Vec::with_capacity(keyframes.len());
    for w in order.windows(2) {
        let (a, b) = (&keyframes[w[0].2], &keyframes[w[1].2]);
        let step = (b.x - a.x).hypot(b.y - a.y);
        steps.push(step);
        total_m += step;
        driven[w[1].2] = total_m;
    }
    steps.sort_by(f64::total_cmp);
    let near = (REVISIT_NEAR * quantile(&steps, 0.5).unwrap_or(0.0)).max(REVISIT_NEAR_M);
    map.covisibility()
        .edges()
        .iter()
        .filter_map(|((a, b), &weight)| {
            let (a, b) = (*index_of.get(a)?, *index_of.get(b)?);
            let (ka, kb) = (&keyframes[a], &keyframes[b]);
            let apart = (kb.x - ka.x).hypot(kb.y - ka.y);
            let path = (driven[b] - driven[a]).abs();
            Some(Edge {
                a,
                b,
                weight,
                revisit: apart <= near && path > REVISIT_DETOUR * apart + REVISIT_SLACK_M,
            })
        })
        .collect()
}

/// The height colour range: [`HEIGHT_QUANTILES`] of the drawn points' z, at least
/// 0.1 m wide ((0, 1) without points).
fn height_range(points: &[[f64; 3]]) -> (f64, f64) {
    let zs: Vec<f64> = points.iter().map(|p| p[2]).collect();
    match (
        quantile(&zs, HEIGHT_QUANTILES.0),
        quantile(&zs, HEIGHT_QUANTILES.1),
    ) {
        (Some(lo), Some(hi)) if hi - lo >= 0.1 => (lo, hi),
        (Some(lo), Some(hi)) => (0.5 * (lo + hi) - 0.05, 0.5 * (lo + hi) + 0.05),
        _ => (0.0, 1.0),
    }
}

impl MapFigure {
    pub(super) fn summary(&self) -> &MapSummary {
        &self.summary
    }

    /// Reads the map at `path`: keyframe poses, covisibility and every `n`-th point
    /// (n = ceil(points / max_points)).
    pub(super) fn load(
        path: &Path,
        options: &MapPlotOptions,
        max_points: usize,
    ) -> anyhow::Result<Self> {
        let opened = open_map(path, OpenOptions::default()).map_err(|e| match e {
            ArchiveError::Io { .. } => anyhow::anyhow!("cannot open the map: {e}"),
            other => anyhow::anyhow!("{}: {other}", path.display()),
        })?;
        let map = &opened.map;
        let sampled = Sampled::read(map, path, max_points)?;
        let Sampled {
            total,
            mut points,
            keyframes,
            order,
            index_of,
        } = sampled;
        let bounds = view_bounds(&points, &keyframes);
        let (bx, by) = bounds;
        points.retain(|p| (bx.0..=bx.1).contains(&p[0]) && (by.0..=by.1).contains(&p[1]));
        points.sort_by(|a, b| a[2].total_cmp(&b[2]));
        let all_edges = classified_edges(map, &index_of, &keyframes, order);
        let covisibility_edges = all_edges.len();
        let revisit_edges = all_edges.iter().filter(|e| e.revisit).count();
        let edges = strongest_edges(all_edges, keyframes.len());
        let height_range = height_range(&points);
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| path.display().to_string());
        Ok(Self {
            name,
            summary: MapSummary {
                keyframes: keyframes.len(),
                points: total,
                drawn: points.len(),
                covisibility_edges,
                revisit_edges,
                drawn_edges: (
                    edges.iter().filter(|e| !e.revisit).count(),
                    edges.iter().filter(|e| e.revisit).count(),
                ),
                height_range,
            },
            keyframes,
            points,
            bounds,
            edges,
            edges_shown: options.edges,
        })
    }

    fn legend_entries(&self) -> Vec<(Symbol, String)> {
        let mut entries = vec![(
            Symbol::Arrow(BLACK),
            format!(
                "keyframe pose ({}), arrow = its x axis",
                self.summary.keyframes
            ),
        )];
        if self.edges_shown {
            let s = &self.summary;
            entries.push((
                Symbol::Line(BLACK, 0.4, 1),
                format!(
                    "covisibility ({STRONGEST_PER_KEYFRAME} strongest per keyframe: {} of {})",
                    s.drawn_edges.0,
                    s.covisibility_edges - s.revisit_edges
                ),
            ));
            entries.push((
                Symbol::Line(REVISIT_MAGENTA, 1.0, 2),
                format!("covisibility on a revisit ({})", s.revisit_edges),
            ));
        }
        entries
    }
}

/// The edges to draw: every revisit edge, and each keyframe's `STRONGEST_PER_KEYFRAME`
/// strongest plain edges (ties: the earlier edge), each edge once.
fn strongest_edges(edges: Vec<Edge>, keyframes: usize) -> Vec<Edge> {
    let mut by_keyframe: Vec<Vec<usize>> = vec![Vec::new(); keyframes];
    for (i, e) in edges.iter().enumerate().filter(|(_, e)| !e.revisit) {
        by_keyframe[e.a].push(i);
        by_keyframe[e.b].push(i);
    }
    let mut keep: Vec<bool> = edges.iter().map(|e| e.revisit).collect();
    for mut list in by_keyframe {
        list.sort_by(|&i, &j| edges[j].weight.cmp(&edges[i].weight).then(i.cmp(&j)));
        for &i in list.iter().take(STRONGEST_PER_KEYFRAME) {
            keep[i] = true;
        }
    }
    edges
        .into_iter()
        .zip(keep)
        .filter_map(|(e, k)| k.then_some(e))
        .collect()
}

impl MapFigure {
    /// The title: the map's name, keyframes and points (drawn).
    fn draw_title<DB: DrawingBackend>(
        &self,
        band: &DrawingArea<DB, Shift>,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let s = &self.summary;
        centred_text(
            band,
            &format!(
                "{}: {}, {} points (drawn {})",
                self.name,
                plural(s.keyframes, "keyframe"),
                grouped(s.points),
                grouped(s.drawn as u64)
            ),
            sizes.title,
            BLACK,
            sizes.pad as i32,
        )
    }

    /// The points coloured by height: single pixels when dense, 2x2 or 3x3 squares when
    /// sparse.
    fn draw_points<DB: DrawingBackend>(&self, chart: &mut Chart2d<'_, DB>) -> anyhow::Result<()> {
        draw_height_points(chart, &self.points, self.summary.height_range)
    }

    /// The covisibility edges drawn: plain ones faint, revisits in magenta on top.
    fn draw_edges<DB: DrawingBackend>(&self, chart: &mut Chart2d<'_, DB>) -> anyhow::Result<()> {
        let segment = |e: &Edge| {
            let (a, b) = (&self.keyframes[e.a], &self.keyframes[e.b]);
            vec![(a.x, a.y), (b.x, b.y)]
        };
        chart
            .draw_series(
                self.edges
                    .iter()
                    .filter(|e| !e.revisit)
                    .map(|e| PathElement::new(segment(e), BLACK.mix(0.4).stroke_width(1))),
            )
            .map_err(draw_error)?;
        chart
            .draw_series(
                self.edges
                    .iter()
                    .filter(|e| e.revisit)
                    .map(|e| PathElement::new(segment(e), REVISIT_MAGENTA.stroke_width(2))),
            )
            .map_err(draw_error)?;
        Ok(())
    }

    /// Keyframe arrows along their x axes (a dot when it points up or down): as long as
    /// the typical keyframe spacing allows, within 16 px and 1.4 text heights; `mpp` is
    /// metres per pixel.
    fn draw_keyframes<DB: DrawingBackend>(
        &self,
        chart: &mut Chart2d<'_, DB>,
        mpp: f64,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let mut steps: Vec<f64> = self
            .keyframes
            .windows(2)
            .map(|w| (w[1].x - w[0].x).hypot(w[1].y - w[0].y) / mpp)
            .collect();
        steps.sort_by(f64::total_cmp);
        let max_px = (1.4 * sizes.text).max(16.0);
        let arrow_px = quantile(&steps, 0.5).map_or(max_px, |m| (0.8 * m).clamp(16.0, max_px));
        let len = arrow_px * mpp;
        for k in &self.keyframes {
            let Some((dx, dy)) = k.heading else {
                chart
                    .draw_series(std::iter::once(Circle::new((k.x, k.y), 3, BLACK.filled())))
                    .map_err(draw_error)?;
                continue;
            };
            let tip = (k.x + dx * len, k.y + dy * len);
            let head = 0.45 * len;
            let base = (tip.0 - dx * head, tip.1 - dy * head);
            let (nx, ny) = (-dy * 0.5 * head, dx * 0.5 * head);
            let corners = [tip, (base.0 + nx, base.1 + ny), (base.0 - nx, base.1 - ny)];
            // A white halo keeps the arrow readable over any point colour.
            chart
                .draw_series([
                    PathElement::new(vec![(k.x, k.y), base], WHITE.stroke_width(5)),
                    PathElement::new(
                        vec![corners[0], corners[1], corners[2], corners[0]],
                        WHITE.stroke_width(3),
                    ),
                ])
                .map_err(draw_error)?;
            chart
                .draw_series([
                    PathElement::new(vec![(k.x, k.y), base], BLACK.stroke_width(2)).into_dyn(),
                    Polygon::new(corners.to_vec(), BLACK.filled()).into_dyn(),
                ])
                .map_err(draw_error)?;
        }
        Ok(())
    }

    /// "the map has no keyframes", centred in the view.
    fn draw_empty_note<DB: DrawingBackend>(
        &self,
        chart: &mut Chart2d<'_, DB>,
        sizes: &Sizes,
    ) -> anyhow::Result<()> {
        let (xr, yr) = self.bounds;
        let style = Sizes::font(sizes.text)
            .color(&GREY)
            .pos(Pos::new(HPos::Center, VPos::Center));
        chart
            .draw_series(std::iter::once(Text::new(
                "the map has no keyframes",
                (0.5 * (xr.0 + xr.1), 0.5 * (yr.0 + yr.1)),
                style,
            )))
            .map_err(draw_error)?;
        Ok(())
    }
}

impl Figure for MapFigure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> anyhow::Result<()> {
        let (width, height) = root.dim_in_pixel();
        let sizes = Sizes::of(width, height);
        root.fill(&WHITE).map_err(draw_error)?;
        let title_h = (1.9 * sizes.title) as u32 + sizes.pad;
        let (title_band, rest) = root.split_vertically(title_h);
        self.draw_title(&title_band, &sizes)?;
        let entries = self.legend_entries();
        let legend_h = legend_height(root, &entries, width, &sizes)?;
        let (_, rest_h) = rest.dim_in_pixel();
        let (main, legend_band) = rest.split_vertically(rest_h.saturating_sub(legend_h));
        let bar_w = (9.0 * sizes.tick) as u32;
        let (chart_area, bar_area) = main.split_horizontally(width.saturating_sub(bar_w));

        let (xr, yr) = self.bounds;
        let (mut chart, mpp) = top_down_chart(&chart_area, xr, yr, &sizes)?;
        self.draw_points(&mut chart)?;
        if self.edges_shown {
            self.draw_edges(&mut chart)?;
        }
        self.draw_keyframes(&mut chart, mpp, &sizes)?;
        if self.keyframes.is_empty() && self.points.is_empty() {
            self.draw_empty_note(&mut chart, &sizes)?;
        }

        // The colour bar spans the plotting area's height.
        let (top, bottom) = {
            let plot_rows = chart.plotting_area().get_pixel_range().1;
            let main_rows = main.get_pixel_range().1;
            (
                (plot_rows.start - main_rows.start).max(0) as u32,
                (main_rows.end - plot_rows.end).max(0) as u32,
            )
        };
        colour_bar(
            &bar_area,
            self.summary.height_range,
            height_colour,
            "height z (m), 2nd-98th percentile",
            &sizes,
            top,
            bottom,
        )?;
        legend(&legend_band, &entries, &sizes)?;
        Ok(())
    }
}
