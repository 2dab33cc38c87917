//! `kfmap inspect`: what a `.kfmap` file holds, and whether every byte of it is sound.

use std::path::PathBuf;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use kfmap_map::archive::{OpenOptions, OpenedMap, open_map};
use kfmap_map::place::GridView;
use serde_json::json;

/// Describe a baked map: header, options, keyframes, points, size breakdown, bounding
/// box, covisibility statistics, gravity pool, `T_map_input` (the levelling bake
/// applied to the dataset's poses) and the place grid relocalization searches.
///
/// Opening reads only the header and the index. --verify also checks the whole-file
/// checksum, every keyframe (its checksum, archive layout and KD-tree: each point
/// must find itself) and the place grid; use it after copying a map to a robot.
///
/// Exit code 2 with a message naming the problem for a missing, truncated, corrupt,
/// wrong-version or wrong-endianness file.
///
/// Example:
///   kfmap inspect campus.kfmap
///   kfmap inspect campus.kfmap --verify --json
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The map file.
    map: PathBuf,
    /// Check the file checksum and every keyframe, including its tree.
    #[arg(long)]
    verify: bool,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Sizes by kind, bytes.
struct Breakdown {
    points: u64,
    covariances: u64,
    trees_and_overhead: u64,
    index: u64,
    place_grid: u64,
}

fn breakdown(m: &OpenedMap) -> Breakdown {
    let entries = &m.index.keyframes;
    let points: u64 = entries.iter().map(|k| k.point_bytes).sum();
    let covariances: u64 = entries.iter().map(|k| k.covariance_bytes).sum();
    let segments: u64 = entries.iter().map(|k| k.len).sum();
    Breakdown {
        points,
        covariances,
        trees_and_overhead: segments - points - covariances,
        index: m.header.index_len,
        place_grid: m.index.place.map_or(0, |p| p.len),
    }
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let started = Instant::now();
    let opened = open_map(&args.map, OpenOptions::default())?;
    let open_ms = started.elapsed().as_secs_f64() * 1e3;
    let verify_ms = if args.verify {
        Some(verify(&opened, args.json)?)
    } else {
        None
    };
    let facts = MapFacts::of(&opened)?;
    let timing = Timing { open_ms, verify_ms };
    if args.json {
        println!("{}", facts_json(&args, &opened, &facts, &timing));
    } else {
        print_facts(&args, &opened, &facts, &timing);
    }
    Ok(())
}

/// How long opening took, and verifying with `--verify`, milliseconds.
struct Timing {
    open_ms: f64,
    verify_ms: Option<f64>,
}

/// Checks the whole-file checksum, every keyframe and the place grid, showing progress
/// (hidden with `json`); milliseconds it took.
fn verify(opened: &OpenedMap, json: bool) -> anyhow::Result<f64> {
    let started = Instant::now();
    opened.verify_payload()?;
    let bar = if json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(opened.map.len() as u64)
    };
    bar.set_style(
        ProgressStyle::with_template("verifying [{bar:40}] {pos}/{len} keyframes, eta {eta}")
            .expect("template")
            .progress_chars("=> "),
    );
    opened.verify_keyframes(|done| bar.set_position(done as u64))?;
    if let Some(place) = &opened.place {
        place.view()?;
    }
    bar.finish_and_clear();
    Ok(started.elapsed().as_secs_f64() * 1e3)
}

/// What the map holds, as printed.
struct MapFacts<'a> {
    points: u64,
    sizes: Breakdown,
    /// Bounding box of every keyframe's box in the map frame, metres.
    lo: [f64; 3],
    hi: [f64; 3],
    covisibility_edges: usize,
    mean_degree: f64,
    essential_edges: usize,
    gravity_pool: usize,
    /// Mean accelerometer spread of the gravity pool, m/s^2 (`None`: empty pool).
    pool_spread: Option<f64>,
    place: Option<GridView<'a>>,
}

impl<'a> MapFacts<'a> {
    /// Gathers the facts of `opened` from its index, keyframe boxes, covisibility graph,
    /// gravity pool and place grid.
    fn of(opened: &'a OpenedMap) -> anyhow::Result<Self> {
        let index = &opened.index;
        let (lo, hi) = map_bounds(opened);
        let covis = opened.map.covisibility();
        let edges = covis.edges();
        let pool = &index.gravity_pool;
        Ok(Self {
            points: index.keyframes.iter().map(|k| k.points).sum(),
            sizes: breakdown(opened),
            lo,
            hi,
            covisibility_edges: edges.len(),
            mean_degree: 2.0 * edges.len() as f64 / covis.len().max(1) as f64,
            essential_edges: covis.essential_graph().len(),
            gravity_pool: pool.len(),
            pool_spread: if pool.is_empty() {
                None
            } else {
                Some(pool.iter().map(|g| g.std).sum::<f64>() / pool.len() as f64)
            },
            place: opened.place.as_ref().map(|p| p.view()).transpose()?,
        })
    }
}

/// The map frame's bounding box of every keyframe's bounding box (all 8 corners).
fn map_bounds(opened: &OpenedMap) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for k in opened.map.keyframes() {
        for corner in 0..8 {
            let b = &k.bbox;
            let local = nalgebra::Point3::new(
                if corner & 1 == 0 { b.min[0] } else { b.max[0] } as f64,
                if corner & 2 == 0 { b.min[1] } else { b.max[1] } as f64,
                if corner & 4 == 0 { b.min[2] } else { b.max[2] } as f64,
            );
            let p = k.pose * local;
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
    }
    (lo, hi)
}

/// `--json`'s object.
fn facts_json(
    args: &Args,
    opened: &OpenedMap,
    f: &MapFacts<'_>,
    timing: &Timing,
) -> serde_json::Value {
    let h = &opened.header;
    let sizes = &f.sizes;
    json!({
        "map": args.map,
        "format_version": h.format_version,
        "creator": h.creator,
        "pointer_width": h.pointer_width,
        "keyframes": opened.map.len(),
        "points": f.points,
        "bytes": opened.file_len(),
        "bytes_points": sizes.points,
        "bytes_covariances": sizes.covariances,
        "bytes_trees_and_overhead": sizes.trees_and_overhead,
        "bytes_index": sizes.index,
        "bytes_place_grid": sizes.place_grid,
        "place_grid": f.place.as_ref().map(|g| json!({
            "resolution_m": g.resolution(),
            "dims": g.dims(),
            "levels": g.levels(),
            "bytes": g.bytes(),
            "index": g.index().0,
            "index_slots": g.index().1,
            "blocks_per_level": g.level_blocks().iter()
                .map(|b| json!({"partial": b.partial, "full": b.full}))
                .collect::<Vec<_>>(),
        })),
        "bbox_min": f.lo,
        "bbox_max": f.hi,
        "covisibility_edges": f.covisibility_edges,
        "covisibility_mean_degree": f.mean_degree,
        "essential_graph_edges": f.essential_edges,
        "gravity_pool": f.gravity_pool,
        "gravity_pool_mean_std": f.pool_spread,
        "map_from_input": opened.index.map_from_input,
        "options": toml::from_str::<toml::Value>(&h.options_toml).ok(),
        "open_ms": timing.open_ms,
        "verified": args.verify,
        "verify_ms": timing.verify_ms,
    })
}

/// Prints the facts for people.
fn print_facts(args: &Args, opened: &OpenedMap, f: &MapFacts<'_>, timing: &Timing) {
    let h = &opened.header;
    let sizes = &f.sizes;
    let (lo, hi) = (f.lo, f.hi);
    let mb = |b: u64| b as f64 / 1e6;
    println!(
        "{} (format {}, written by {})",
        args.map.display(),
        h.format_version,
        h.creator
    );
    println!(
        "  {} keyframes, {} points, {:.1} MB: points {:.1}, covariances {:.1}, trees + overhead {:.1}, index {:.3}",
        opened.map.len(),
        f.points,
        mb(opened.file_len()),
        mb(sizes.points),
        mb(sizes.covariances),
        mb(sizes.trees_and_overhead),
        mb(sizes.index)
    );
    println!(
        "  bounds [{:.1}, {:.1}, {:.1}] .. [{:.1}, {:.1}, {:.1}] m",
        lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
    );
    println!(
        "  covisibility: {} edges, mean degree {:.1}, essential graph {} edges",
        f.covisibility_edges, f.mean_degree, f.essential_edges
    );
    match &f.place {
        Some(g) => {
            let blocks = g.level_blocks();
            let per_level: Vec<String> = blocks
                .iter()
                .map(|b| format!("{}+{}", b.partial, b.full))
                .collect();
            let (index, slots) = g.index();
            println!(
                "  place grid (relocalization): {:?} voxels of {} m, {} levels, {} block levels \
                 of 8^3 ({} wholly marked) found by a {index} of {slots}, {:.3} MB ({:.2} % of \
                 the file); per level partly+wholly marked blocks: {}",
                g.dims(),
                g.resolution(),
                g.levels(),
                blocks.iter().map(|b| b.partial + b.full).sum::<usize>(),
                blocks.iter().map(|b| b.full).sum::<usize>(),
                mb(sizes.place_grid),
                100.0 * sizes.place_grid as f64 / opened.file_len() as f64,
                per_level.join(" ")
            );
        }
        None => println!("  place grid: none (relocalization refused; bake the map again)"),
    }
    match f.pool_spread {
        Some(s) => println!(
            "  gravity pool: {} keyframes, mean accelerometer spread {s:.3} m/s^2",
            f.gravity_pool
        ),
        None => println!("  gravity pool: empty"),
    }
    println!(
        "  {}",
        super::report::map_from_input_line(
            kfmap_geometry::geometry::pose_from_xyz_quat(opened.index.map_from_input).as_ref()
        )
    );
    println!("  options:");
    for line in h.options_toml.lines().filter(|l| !l.is_empty()) {
        println!("    {line}");
    }
    match timing.verify_ms {
        Some(ms) => println!("  verified: checksum and every keyframe's tree ({ms:.0} ms)"),
        None => println!(
            "  opened in {:.2} ms (pass --verify to check every byte)",
            timing.open_ms
        ),
    }
}
