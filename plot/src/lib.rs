//! Pictures of kfmap's work: a baked map from above, a trajectory against its reference,
//! and a recorded localization run (what RViz shows of a localizer), as PNG or SVG.
//! `kfmap plot` and `kfmap demo` draw through it; the command's `--help` says what each
//! picture shows.

mod draw;
mod map;
mod run;
mod trajectory;

use std::path::Path;

pub use draw::{MAX_SIDE, MIN_SIDE, check_size, grouped, ms_label, plural};
pub use map::MapSummary;
pub use run::{RunSummary, RunTopics};
pub use trajectory::{DEFAULT_MAX_DT, TrajectoryOptions, TrajectorySummary};

use draw::Format;
use map::MapFigure;
use run::RunFigure;
use trajectory::TrajectoryFigure;

/// How to draw a map.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MapPlotOptions {
    /// Draw the covisibility edges between keyframes (revisits distinct).
    pub edges: bool,
    /// Picture width, pixels.
    pub width: u32,
    /// Picture height, pixels.
    pub height: u32,
}

impl Default for MapPlotOptions {
    fn default() -> Self {
        Self {
            edges: true,
            width: 1600,
            height: 1200,
        }
    }
}

/// Draws the map file `map` to `out` (.png or .svg): points from above coloured by
/// height, keyframe poses, covisibility edges with `options.edges`.
pub fn render_map(map: &Path, out: &Path, options: &MapPlotOptions) -> anyhow::Result<()> {
    render_map_summary(map, out, options).map(|_| ())
}

/// As [`render_map`], returning what the picture shows.
pub fn render_map_summary(
    map: &Path,
    out: &Path,
    options: &MapPlotOptions,
) -> anyhow::Result<MapSummary> {
    let format = draw::check_out(out)?;
    draw::check_size(options.width, options.height)?;
    let max_points = match format {
        Format::Png => map::MAX_POINTS_PNG,
        Format::Svg => map::MAX_POINTS_SVG,
    };
    let figure = MapFigure::load(map, options, max_points)?;
    draw::render_to_file(&figure, out, format, options.width, options.height)?;
    Ok(figure.summary().clone())
}

/// The files of a trajectory picture.
#[derive(Debug, Clone, Copy)]
pub struct TrajectoryPlotInputs<'a> {
    /// Estimated trajectory, TUM.
    pub estimate: &'a Path,
    /// Reference trajectory, TUM, same frame as the estimate.
    pub reference: &'a Path,
    /// `kfmap localize --json-lines` output whose lost/failed/degraded scans are marked.
    pub scan_log: Option<&'a Path>,
    /// Picture title; default: the two file names.
    pub title: Option<&'a str>,
}

/// Draws the estimate against the reference to `out` (.png or .svg), `width` x
/// `height` pixels; poses are matched by stamp within 5 ms.
pub fn render_trajectory(
    inputs: &TrajectoryPlotInputs,
    out: &Path,
    width: u32,
    height: u32,
) -> anyhow::Result<()> {
    render_trajectory_summary(inputs, out, width, height, &TrajectoryOptions::default()).map(|_| ())
}

/// As [`render_trajectory`] with `options` (stamp tolerance, alignment), returning
/// what the picture shows.
pub fn render_trajectory_summary(
    inputs: &TrajectoryPlotInputs,
    out: &Path,
    width: u32,
    height: u32,
    options: &TrajectoryOptions,
) -> anyhow::Result<TrajectorySummary> {
    let format = draw::check_out(out)?;
    draw::check_size(width, height)?;
    let figure = TrajectoryFigure::load(inputs, options)?;
    draw::render_to_file(&figure, out, format, width, height)?;
    Ok(figure.summary().clone())
}

/// Draws the localization run recorded in `bag` to `out` (.png or .svg), `width` x
/// `height` pixels, returning what the picture shows.
pub fn render_run_summary(
    bag: &Path,
    topics: &RunTopics,
    out: &Path,
    width: u32,
    height: u32,
) -> anyhow::Result<RunSummary> {
    let format = draw::check_out(out)?;
    draw::check_size(width, height)?;
    let max_points = match format {
        Format::Png => map::MAX_POINTS_PNG,
        Format::Svg => map::MAX_POINTS_SVG,
    };
    let figure = RunFigure::load(bag, topics, max_points)?;
    draw::render_to_file(&figure, out, format, width, height)?;
    Ok(figure.summary().clone())
}
