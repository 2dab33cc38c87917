//! Pieces both pictures share: the output format, the canvas, the embedded font, text
//! sizes, colour maps, the colour bar, the legend band and equal-aspect axes.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::Context;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// The font family every text of the pictures uses (registered from the embedded file).
pub(super) const FONT: &str = "sans-serif";

/// DejaVu Sans reduced to the characters the pictures use (licence beside it): plotters
/// renders text through ab_glyph from font bytes, so no system font is needed.
static FONT_BYTES: &[u8] = include_bytes!("DejaVuSans-subset.ttf");

/// Registers the embedded font once.
pub(super) fn register_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, FONT_BYTES).is_ok()
    });
    anyhow::ensure!(ok, "the embedded plot font is unreadable");
    Ok(())
}

/// What `--out` is written as, from its extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Format {
    Png,
    Svg,
}

impl Format {
    /// The format of `out`: `.png` or `.svg` (any case); anything else is an error.
    pub(super) fn of(out: &Path) -> anyhow::Result<Self> {
        let ext = out
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("png") => Ok(Self::Png),
            Some("svg") => Ok(Self::Svg),
            Some(other) => anyhow::bail!(
                "{}: unknown picture format '.{other}'; the output must end in .png or .svg",
                out.display()
            ),
            None => anyhow::bail!(
                "{}: no file extension; the output must end in .png or .svg",
                out.display()
            ),
        }
    }
}

/// A picture that draws itself on any plotters backend.
pub(super) trait Figure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> anyhow::Result<()>;
}

/// A drawing error as an `anyhow` error.
pub(super) fn draw_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("drawing failed: {e}")
}

/// Smallest and largest accepted picture side, pixels.
pub const MIN_SIDE: u32 = 300;
pub const MAX_SIDE: u32 = 10_000;

/// Renders `figure` at `width` x `height` pixels and writes it to `out` atomically (a
/// temporary file beside it, renamed when complete): a failed render leaves nothing.
pub(super) fn render_to_file(
    figure: &impl Figure,
    out: &Path,
    format: Format,
    width: u32,
    height: u32,
) -> anyhow::Result<()> {
    check_size(width, height)?;
    register_font()?;
    let bytes = match format {
        Format::Png => {
            let mut rgb = vec![255u8; width as usize * height as usize * 3];
            {
                let root =
                    BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
                figure.draw(&root)?;
                root.present().map_err(draw_error)?;
            }
            encode_png(&rgb, width, height)?
        }
        Format::Svg => {
            let mut svg = String::new();
            {
                let root = SVGBackend::with_string(&mut svg, (width, height)).into_drawing_area();
                figure.draw(&root)?;
                root.present().map_err(draw_error)?;
            }
            svg.into_bytes()
        }
    };
    kfmap_geometry::io::write_atomic(out, &bytes).context("cannot write the picture")?;
    Ok(())
}

/// Checks, before any work, that `out` can be a picture: a known extension and an
/// existing folder.
pub(super) fn check_out(out: &Path) -> anyhow::Result<Format> {
    let format = Format::of(out)?;
    let dir = out.parent().filter(|d| !d.as_os_str().is_empty());
    if let Some(dir) = dir {
        anyhow::ensure!(
            dir.is_dir(),
            "{}: the output folder {} does not exist",
            out.display(),
            dir.display()
        );
    }
    Ok(format)
}

/// Refuses sizes outside `MIN_SIDE..=MAX_SIDE`.
pub fn check_size(width: u32, height: u32) -> anyhow::Result<()> {
    anyhow::ensure!(
        (MIN_SIDE..=MAX_SIDE).contains(&width) && (MIN_SIDE..=MAX_SIDE).contains(&height),
        "picture size {width}x{height} is outside {MIN_SIDE}..={MAX_SIDE} pixels a side"
    );
    Ok(())
}

/// RGB bytes as a PNG file.
fn encode_png(rgb: &[u8], width: u32, height: u32) -> anyhow::Result<Vec<u8>> {
    let mut bytes = Vec::new();
    let mut encoder = png::Encoder::new(&mut bytes, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().context("PNG encoder")?;
    writer.write_image_data(rgb).context("PNG encoder")?;
    writer.finish().context("PNG encoder")?;
    Ok(bytes)
}

/// Text sizes and spacing for a canvas, pixels: readable at 1600x1200, scaled with it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Sizes {
    pub title: f64,
    pub text: f64,
    pub tick: f64,
    /// Generic gap.
    pub pad: u32,
}

impl Sizes {
    pub(super) fn of(width: u32, height: u32) -> Self {
        let s = (width as f64 / 1600.0).min(height as f64 / 1200.0);
        Self {
            title: (30.0 * s).clamp(15.0, 64.0),
            text: (21.0 * s).clamp(12.0, 44.0),
            tick: (19.0 * s).clamp(11.0, 40.0),
            pad: (12.0 * s).clamp(5.0, 30.0).round() as u32,
        }
    }

    pub(super) fn font(size: f64) -> TextStyle<'static> {
        TextStyle::from((FONT, size).into_font()).color(&BLACK)
    }
}

/// Draws `text` centred in `area` (horizontally) at pixel row `y` of the area.
pub(super) fn centred_text<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    text: &str,
    size: f64,
    color: RGBColor,
    y: i32,
) -> anyhow::Result<()> {
    let (w, _) = area.dim_in_pixel();
    let style = Sizes::font(size)
        .color(&color)
        .pos(Pos::new(HPos::Center, VPos::Top));
    area.draw_text(text, &style, (w as i32 / 2, y))
        .map_err(draw_error)
}

/// Turbo colour map (Google, polynomial fit), `t` in 0..=1: dark blue, cyan, green,
/// yellow, red.
pub(super) fn turbo(t: f64) -> RGBColor {
    let x = t.clamp(0.0, 1.0);
    let r = 0.135_721_38
        + x * (4.615_392_6
            + x * (-42.660_322_58
                + x * (132.131_082_34 + x * (-152.942_393_96 + x * 59.286_379_43))));
    let g = 0.091_402_61
        + x * (2.194_188_39
            + x * (4.842_966_58 + x * (-14.185_033_33 + x * (4.277_298_57 + x * 2.829_566_04))));
    let b = 0.106_673_3
        + x * (12.641_946_08
            + x * (-60.582_048_36
                + x * (110.362_767_71 + x * (-89.903_109_12 + x * 27.348_249_73))));
    rgb_unit(r, g, b)
}

/// Viridis colour map (polynomial fit), `t` in 0..=1: dark purple, blue, green, yellow.
pub(super) fn viridis(t: f64) -> RGBColor {
    const C: [[f64; 3]; 7] = [
        [
            0.277_727_327_223_417_7,
            0.005_407_344_544_966_578,
            0.334_099_805_335_306_1,
        ],
        [
            0.105_093_043_108_577_4,
            1.404_613_529_898_575,
            1.384_590_162_594_685,
        ],
        [
            -0.330_861_828_725_556_3,
            0.214_847_559_468_213,
            0.095_095_163_028_236_59,
        ],
        [
            -4.634_230_498_983_486,
            -5.799_100_973_351_585,
            -19.332_440_956_279_87,
        ],
        [
            6.228_269_936_347_081,
            14.179_933_366_805_09,
            56.690_552_600_681_05,
        ],
        [
            4.776_384_997_670_288,
            -13.745_145_377_746_01,
            -65.353_032_633_372_34,
        ],
        [
            -5.435_455_855_934_631,
            4.645_852_612_178_535,
            26.312_435_249_583_2,
        ],
    ];
    let x = t.clamp(0.0, 1.0);
    let channel = |c: usize| C.iter().rev().fold(0.0, |acc, row| acc * x + row[c]);
    rgb_unit(channel(0), channel(1), channel(2))
}

fn rgb_unit(r: f64, g: f64, b: f64) -> RGBColor {
    let byte = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    RGBColor(byte(r), byte(g), byte(b))
}

/// Grey of the reference trajectory and faint lines.
pub(super) const GREY: RGBColor = RGBColor(150, 150, 150);
/// Marks of lost or failed scans.
pub(super) const LOST_RED: RGBColor = RGBColor(228, 26, 28);
/// Marks of degraded scans.
pub(super) const DEGRADED_ORANGE: RGBColor = RGBColor(255, 140, 0);
/// Distinct (revisit) edges.
pub(super) const REVISIT_MAGENTA: RGBColor = RGBColor(214, 0, 214);

/// `v` with `decimals` decimals, trailing zeros dropped, never "-0".
fn trimmed(v: f64, decimals: usize) -> String {
    let mut s = format!("{v:.decimals$}");
    if s.contains('.') {
        s = s.trim_end_matches('0').trim_end_matches('.').to_string();
    }
    if s == "-0" { "0".to_string() } else { s }
}

/// Tick labels for an axis spanning `span`: one decimal more than a tenth of the span
/// needs (0.004 m of error gets 0.0005 steps, 50 m gets 5), trailing zeros dropped.
pub(super) fn tick_label(span: f64) -> impl Fn(&f64) -> String {
    let step = (span.abs() / 10.0).max(1e-9);
    let decimals = ((-step.log10()).ceil() + 1.0).clamp(0.0, 9.0) as usize;
    move |v| trimmed(*v, decimals)
}

/// A duration in seconds as milliseconds, shortest form: 0.005 -> "5".
pub fn ms_label(seconds: f64) -> String {
    format!("{}", (seconds * 1e9).round() / 1e6)
}

/// "1 keyframe", "2 keyframes".
pub fn plural(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{} {noun}s", grouped(n as u64))
    }
}

/// `n` with thin groups of three digits: 412 345.
pub fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// Data bounds of `points` (x, y), padded by 4 % and at least `min_span` metres wide.
pub(super) fn padded_bounds(
    points: impl Iterator<Item = (f64, f64)>,
    min_span: f64,
) -> ((f64, f64), (f64, f64)) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for (x, y) in points {
        if x.is_finite() && y.is_finite() {
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
    }
    let axis = |a: usize| {
        if lo[a] > hi[a] {
            return (-min_span / 2.0, min_span / 2.0);
        }
        let span = (hi[a] - lo[a]).max(min_span);
        let mid = 0.5 * (lo[a] + hi[a]);
        (mid - 0.52 * span, mid + 0.52 * span)
    };
    (axis(0), axis(1))
}

/// Widens one of the ranges so a metre is as many pixels along x as along y in a
/// plotting area of `pixels`.
pub(super) fn equal_aspect(
    x: (f64, f64),
    y: (f64, f64),
    pixels: (u32, u32),
) -> ((f64, f64), (f64, f64)) {
    let (pw, ph) = (pixels.0.max(1) as f64, pixels.1.max(1) as f64);
    let scale = ((x.1 - x.0) / pw).max((y.1 - y.0) / ph);
    let widen = |r: (f64, f64), px: f64| {
        let mid = 0.5 * (r.0 + r.1);
        (mid - 0.5 * scale * px, mid + 0.5 * scale * px)
    };
    (widen(x, pw), widen(y, ph))
}

pub(super) type Chart2d<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

/// Axis titles, tick labels (about `ticks` per axis, as many decimals as the span
/// needs) and the light grid of every chart here.
pub(super) fn draw_grid<DB: DrawingBackend>(
    chart: &mut Chart2d<'_, DB>,
    titles: [&str; 2],
    spans: (f64, f64),
    ticks: (usize, usize),
    sizes: &Sizes,
) -> anyhow::Result<()> {
    let (x_label, y_label) = (tick_label(spans.0), tick_label(spans.1));
    chart
        .configure_mesh()
        .x_desc(titles[0])
        .y_desc(titles[1])
        .x_label_formatter(&x_label)
        .y_label_formatter(&y_label)
        .label_style(Sizes::font(sizes.tick))
        .axis_desc_style(Sizes::font(sizes.text))
        .bold_line_style(RGBColor(215, 215, 215).stroke_width(1))
        .light_line_style(RGBColor(240, 240, 240).stroke_width(1))
        .x_labels(ticks.0)
        .y_labels(ticks.1)
        .draw()
        .map_err(draw_error)
}

/// A value-over-time chart on `area` (its right margin `bar_w` wide, under the colour
/// bar of the view above): `times` on x, `0..top` on y, axis titles, labels and grid.
pub(super) fn time_chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    bar_w: u32,
    times: (f64, f64),
    top: f64,
    titles: [&str; 2],
    sizes: &Sizes,
) -> anyhow::Result<Chart2d<'a, DB>> {
    let mut chart = ChartBuilder::on(area)
        .margin(sizes.pad)
        .margin_right(bar_w + 2 * sizes.pad)
        .x_label_area_size((2.6 * sizes.tick) as u32)
        .y_label_area_size((4.2 * sizes.tick) as u32)
        .build_cartesian_2d(times.0..times.1, 0.0..top)
        .map_err(draw_error)?;
    draw_grid(&mut chart, titles, (times.1 - times.0, top), (12, 6), sizes)?;
    Ok(chart)
}

/// A top-down chart on `area`: x right, y up, equal aspect, metre labels and grid.
/// Returns it with its scale, metres per pixel.
pub(super) fn top_down_chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    x: (f64, f64),
    y: (f64, f64),
    sizes: &Sizes,
) -> anyhow::Result<(Chart2d<'a, DB>, f64)> {
    // Wide enough for the longest y label (large coordinates, e.g. UTM, included).
    let font = Sizes::font(sizes.tick);
    let mut label_w = 0;
    let y_label = tick_label(y.1 - y.0);
    for v in [y.0, y.1, y.0 - 0.25 * (y.1 - y.0), y.1 + 0.25 * (y.1 - y.0)] {
        let (w, _) = area
            .estimate_text_size(&y_label(&v), &font)
            .map_err(draw_error)?;
        label_w = label_w.max(w);
    }
    let y_label_area = (label_w as f64 + 2.4 * sizes.tick).max(4.2 * sizes.tick) as u32;
    let build = |x: (f64, f64), y: (f64, f64)| {
        ChartBuilder::on(area)
            .margin(sizes.pad)
            .margin_right(2 * sizes.pad)
            .x_label_area_size((2.6 * sizes.tick) as u32)
            .y_label_area_size(y_label_area)
            .build_cartesian_2d(x.0..x.1, y.0..y.1)
            .map_err(draw_error)
    };
    let probe = build(x, y)?;
    let pixels = probe.plotting_area().dim_in_pixel();
    drop(probe);
    let (x, y) = equal_aspect(x, y, pixels);
    let mut chart = build(x, y)?;
    draw_grid(
        &mut chart,
        ["x (m)", "y (m)"],
        (x.1 - x.0, y.1 - y.0),
        (10, 10),
        sizes,
    )?;
    let metres_per_pixel = (x.1 - x.0) / pixels.0.max(1) as f64;
    Ok((chart, metres_per_pixel))
}

/// A vertical colour bar of `cmap` over `range` with value labels and `label` beside
/// it, `top_margin` and `bottom_margin` pixels from the ends of `area`.
pub(super) fn colour_bar<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    range: (f64, f64),
    cmap: fn(f64) -> RGBColor,
    label: &str,
    sizes: &Sizes,
    top_margin: u32,
    bottom_margin: u32,
) -> anyhow::Result<()> {
    let (lo, hi) = range;
    let span = (hi - lo).max(1e-9);
    let mut chart = ChartBuilder::on(area)
        .margin_top(top_margin)
        .margin_bottom(bottom_margin)
        .margin_left(sizes.pad)
        .margin_right(sizes.pad)
        .set_label_area_size(LabelAreaPosition::Right, (5.6 * sizes.tick) as u32)
        .build_cartesian_2d(0.0..1.0, lo..hi)
        .map_err(draw_error)?;
    const STEPS: usize = 128;
    chart
        .draw_series((0..STEPS).map(|i| {
            let a = lo + span * i as f64 / STEPS as f64;
            let b = lo + span * (i + 1) as f64 / STEPS as f64;
            let c = cmap((i as f64 + 0.5) / STEPS as f64);
            Rectangle::new([(0.0, a), (1.0, b)], c.filled())
        }))
        .map_err(draw_error)?;
    let label_fmt = tick_label(span);
    chart
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .set_all_tick_mark_size(sizes.pad / 2 + 2)
        .y_labels(8)
        .y_label_formatter(&label_fmt)
        .y_desc(label)
        .label_style(Sizes::font(sizes.tick))
        .axis_desc_style(Sizes::font(sizes.text))
        .draw()
        .map_err(draw_error)?;
    chart
        .draw_series(std::iter::once(Rectangle::new(
            [(0.0, lo), (1.0, hi)],
            BLACK.stroke_width(1),
        )))
        .map_err(draw_error)?;
    Ok(())
}

/// Colour of a height, `t` in 0..=1 over the colour range: turbo without its darkest
/// ends (blue to dark red), so the lowest points stay distinct from black arrows.
pub(super) fn height_colour(t: f64) -> RGBColor {
    turbo(0.1 + 0.85 * t.clamp(0.0, 1.0))
}

/// Draws `points` (x, y, z; sorted by z, so the highest are drawn last, as seen from
/// above) coloured by height over `height_range`: squares of 2-3 pixels when the view
/// has room for them (a thinned cloud), single pixels when not.
pub(super) fn draw_height_points<DB: DrawingBackend>(
    chart: &mut Chart2d<'_, DB>,
    points: &[[f64; 3]],
    height_range: (f64, f64),
) -> anyhow::Result<()> {
    let (pw, ph) = chart.plotting_area().dim_in_pixel();
    let (lo, hi) = height_range;
    let colour = |z: f64| height_colour((z - lo) / (hi - lo));
    let room = pw as f64 * ph as f64 / points.len().max(1) as f64;
    let side = if room >= 40.0 {
        3
    } else if room >= 10.0 {
        2
    } else {
        1
    };
    if side > 1 {
        chart
            .draw_series(points.iter().map(|p| {
                EmptyElement::at((p[0], p[1]))
                    + Rectangle::new([(0, 0), (side, side)], colour(p[2]).filled())
            }))
            .map_err(draw_error)?;
    } else {
        chart
            .draw_series(
                points
                    .iter()
                    .map(|p| Pixel::new((p[0], p[1]), colour(p[2]))),
            )
            .map_err(draw_error)?;
    }
    Ok(())
}

/// The areas of a two-panel figure (the trajectory and the recorded-run pictures): a
/// title band (the title and a statistics line under it), a top view with a colour bar
/// at its right, the legend band (drawn), and a lower panel as wide as the view.
pub(super) struct Panels<DB: DrawingBackend> {
    pub sizes: Sizes,
    /// The whole top band (view and colour bar), for the bar's margins.
    top: DrawingArea<DB, Shift>,
    pub view: DrawingArea<DB, Shift>,
    bar: DrawingArea<DB, Shift>,
    pub bottom: DrawingArea<DB, Shift>,
    /// The colour bar's width, pixels (the lower panel keeps it as a right margin).
    pub bar_w: u32,
}

impl<DB: DrawingBackend> Panels<DB> {
    /// Fills `root` white, draws the title band and splits the rest: the top view takes
    /// `top_share` of what the legend (of `entries`) leaves.
    pub(super) fn of(
        root: &DrawingArea<DB, Shift>,
        title: &str,
        stats: &str,
        entries: &[(Symbol, String)],
        top_share: f64,
    ) -> anyhow::Result<Self> {
        let (width, height) = root.dim_in_pixel();
        let sizes = Sizes::of(width, height);
        root.fill(&WHITE).map_err(draw_error)?;
        let title_h = (1.5 * sizes.title + 1.6 * sizes.text) as u32 + 2 * sizes.pad;
        let (title_band, rest) = root.split_vertically(title_h);
        centred_text(&title_band, title, sizes.title, BLACK, sizes.pad as i32)?;
        centred_text(
            &title_band,
            stats,
            sizes.text,
            RGBColor(60, 60, 60),
            (1.4 * sizes.title) as i32 + sizes.pad as i32,
        )?;
        let legend_h = legend_height(root, entries, width, &sizes)?;
        let (_, rest_h) = rest.dim_in_pixel();
        let top_h = ((rest_h.saturating_sub(legend_h)) as f64 * top_share) as u32;
        let (top, rest) = rest.split_vertically(top_h);
        let (legend_band, bottom) = rest.split_vertically(legend_h);
        let bar_w = (9.0 * sizes.tick) as u32;
        let (view, bar) = top.split_horizontally(width.saturating_sub(bar_w));
        legend(&legend_band, entries, &sizes)?;
        Ok(Self {
            sizes,
            top,
            view,
            bar,
            bottom,
            bar_w,
        })
    }

    /// The colour bar beside the view, as tall as the view's plotting rows `view_rows`.
    pub(super) fn colour_bar(
        &self,
        view_rows: std::ops::Range<i32>,
        range: (f64, f64),
        cmap: fn(f64) -> RGBColor,
        label: &str,
    ) -> anyhow::Result<()> {
        let main_rows = self.top.get_pixel_range().1;
        colour_bar(
            &self.bar,
            range,
            cmap,
            label,
            &self.sizes,
            (view_rows.start - main_rows.start).max(0) as u32,
            (main_rows.end - view_rows.end).max(0) as u32,
        )
    }
}

/// A legend entry's symbol.
#[derive(Debug, Clone, Copy)]
pub(super) enum Symbol {
    /// A line of this colour, opacity and width.
    Line(RGBColor, f64, u32),
    /// Short segments across a colour map.
    Gradient(fn(f64) -> RGBColor),
    /// A filled arrow.
    Arrow(RGBColor),
    /// An x.
    Cross(RGBColor),
    /// A filled triangle.
    Triangle(RGBColor),
    /// A ring.
    Ring(RGBColor),
}

/// Width of a legend symbol, pixels.
fn symbol_width(sizes: &Sizes) -> i32 {
    (2.4 * sizes.text) as i32
}

/// Legend rows: entries greedily packed into lines no wider than `width`.
fn legend_rows<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(Symbol, String)],
    width: u32,
    sizes: &Sizes,
) -> anyhow::Result<Vec<(Vec<usize>, i32)>> {
    let gap = (0.5 * sizes.text) as i32;
    let between = (1.6 * sizes.text) as i32;
    let font = Sizes::font(sizes.text);
    let mut rows: Vec<(Vec<usize>, i32)> = Vec::new();
    for (i, (_, text)) in entries.iter().enumerate() {
        let (tw, _) = area.estimate_text_size(text, &font).map_err(draw_error)?;
        let w = symbol_width(sizes) + gap + tw as i32;
        match rows.last_mut() {
            Some((row, used)) if *used + between + w <= width as i32 => {
                row.push(i);
                *used += between + w;
            }
            _ => rows.push((vec![i], w)),
        }
    }
    Ok(rows)
}

/// Height a legend of `entries` needs across `width` pixels.
pub(super) fn legend_height<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(Symbol, String)],
    width: u32,
    sizes: &Sizes,
) -> anyhow::Result<u32> {
    let rows = legend_rows(area, entries, width, sizes)?.len().max(1);
    Ok((rows as f64 * 1.6 * sizes.text) as u32 + sizes.pad)
}

/// Draws `entries` centred in `area`, in rows, outside any data.
pub(super) fn legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(Symbol, String)],
    sizes: &Sizes,
) -> anyhow::Result<()> {
    let (width, height) = area.dim_in_pixel();
    let rows = legend_rows(area, entries, width, sizes)?;
    let row_h = (1.6 * sizes.text) as i32;
    let top = (height as i32 - row_h * rows.len() as i32) / 2;
    let gap = (0.5 * sizes.text) as i32;
    let between = (1.6 * sizes.text) as i32;
    let font = Sizes::font(sizes.text).pos(Pos::new(HPos::Left, VPos::Center));
    let sw = symbol_width(sizes);
    for (r, (row, used)) in rows.iter().enumerate() {
        let cy = top + r as i32 * row_h + row_h / 2;
        let mut x = (width as i32 - used) / 2;
        for &i in row {
            let (symbol, text) = &entries[i];
            draw_symbol(area, *symbol, x, cy, sw, sizes)?;
            x += sw + gap;
            area.draw_text(text, &font, (x, cy)).map_err(draw_error)?;
            let (tw, _) = area.estimate_text_size(text, &font).map_err(draw_error)?;
            x += tw as i32 + between;
        }
    }
    Ok(())
}

fn draw_symbol<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    symbol: Symbol,
    x: i32,
    cy: i32,
    w: i32,
    sizes: &Sizes,
) -> anyhow::Result<()> {
    let r = (0.35 * sizes.text) as i32;
    let mid = (x + w / 2, cy);
    match symbol {
        Symbol::Line(c, alpha, width) => area.draw(&PathElement::new(
            vec![(x, cy), (x + w, cy)],
            c.mix(alpha).stroke_width(width),
        )),
        Symbol::Gradient(cmap) => {
            let n = 6;
            for k in 0..n {
                let a = x + w * k / n;
                let b = x + w * (k + 1) / n;
                area.draw(&PathElement::new(
                    vec![(a, cy), (b, cy)],
                    cmap(k as f64 / (n - 1) as f64).stroke_width(4),
                ))
                .map_err(draw_error)?;
            }
            Ok(())
        }
        Symbol::Arrow(c) => {
            let head = (0.45 * w as f64) as i32;
            area.draw(&PathElement::new(
                vec![(x, cy), (x + w - head, cy)],
                c.stroke_width(2),
            ))
            .map_err(draw_error)?;
            area.draw(&Polygon::new(
                vec![
                    (x + w, cy),
                    (x + w - head, cy - head / 2),
                    (x + w - head, cy + head / 2),
                ],
                c.filled(),
            ))
        }
        Symbol::Cross(c) => area.draw(&Cross::new(mid, r, c.stroke_width(3))),
        Symbol::Triangle(c) => area.draw(&TriangleMarker::new(mid, r + 1, c.filled())),
        Symbol::Ring(c) => area.draw(&Circle::new(mid, r + 1, c.stroke_width(2))),
    }
    .map_err(draw_error)
}

/// The `q`-quantile (0..=1) of sorted values by nearest rank, the definition of
/// `kfmap_geometry::percentile`; `None` when empty.
pub(super) fn quantile(sorted: &[f64], q: f64) -> Option<f64> {
    (!sorted.is_empty()).then(|| kfmap_geometry::percentile::percentile(sorted, q))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_and_labels() {
        assert_eq!(Format::of(Path::new("a/b.PNG")).unwrap(), Format::Png);
        assert_eq!(Format::of(Path::new("b.svg")).unwrap(), Format::Svg);
        assert!(Format::of(Path::new("b.jpg")).is_err());
        assert!(Format::of(Path::new("b")).is_err());
        assert_eq!(trimmed(-0.0001, 2), "0");
        assert_eq!(trimmed(12.5, 2), "12.5");
        let small = tick_label(0.004);
        assert_eq!(small(&0.0005), "0.0005");
        assert_eq!(small(&0.001), "0.001");
        let large = tick_label(50.0);
        assert_eq!(large(&-20.0), "-20");
        assert_eq!(large(&2.5), "2.5");
        assert_eq!(grouped(412_345), "412 345");
        assert_eq!(ms_label(0.005), "5");
        assert_eq!(ms_label(0.0125), "12.5");
        assert_eq!(ms_label(1e-7), "0.0001");
        assert_eq!(grouped(300), "300");
        assert_eq!(grouped(1_000_000), "1 000 000");
    }

    #[test]
    fn equal_aspect_widens_the_short_side() {
        let (x, y) = equal_aspect((0.0, 10.0), (0.0, 10.0), (200, 100));
        assert!(((x.1 - x.0) - 20.0).abs() < 1e-9);
        assert!(((y.1 - y.0) - 10.0).abs() < 1e-9);
        assert!((x.0 + 5.0).abs() < 1e-9);
    }

    #[test]
    fn colour_maps_run_dark_to_bright() {
        let lum = |c: RGBColor| 0.3 * c.0 as f64 + 0.59 * c.1 as f64 + 0.11 * c.2 as f64;
        assert!(lum(viridis(0.0)) < lum(viridis(0.5)));
        assert!(lum(viridis(0.5)) < lum(viridis(1.0)));
        // The part of turbo the height colours use: blue to red.
        assert!(turbo(0.1).2 > turbo(0.1).0 && turbo(0.1).2 > turbo(0.1).1);
        assert!(turbo(0.95).0 > turbo(0.95).1 && turbo(0.95).0 > turbo(0.95).2);
    }
}
