//! How often the place search (relocalization's proposals, before verification) finds
//! the right place on real data: `../shared/data/balm_os0`, place grid of scans 0-115
//! at their reference poses, each of scans 116-176 searched over the whole mapped area
//! with no guess (up found from the scan itself). Prints the rank of the first
//! proposal within `RIGHT_M` / `RIGHT_DEG` of the reference, and the search time.
//!
//! ```sh
//! cargo run --release -p kfmap-map --example place_search [RESOLUTION]
//! ```

use std::time::Instant;

use kfmap_geometry::geometry::{rotation_distance, translation_distance};
use kfmap_geometry::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_map::place::{
    Columns, GridBuilder, GridParams, RelocalizeParams, ScanUp, own_up, propose,
};
use kfmap_testdata::shared_data_dir;
use nalgebra::Point3;

const MAP_SCANS: usize = 116;
/// A proposal this close to the reference is in the verifying registration's basin.
const RIGHT_M: f64 = 1.5;
const RIGHT_DEG: f64 = 10.0;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let Some(data) = shared_data_dir() else {
        println!("../shared/data is not beside this checkout: nothing to measure");
        return Ok(());
    };
    let dir = data.join("balm_os0");
    let resolution: f64 = std::env::args().nth(1).map_or(Ok(1.0), |s| s.parse())?;
    let params = GridParams {
        resolution,
        ..GridParams::default()
    };
    params.validate()?;
    let poses = read_trajectory(&dir.join("poses.txt"))?.poses;
    let scan = |i: usize| {
        read_cloud(
            &dir.join(format!("scans/{i:06}.pcd")),
            &ReadOptions::default(),
        )
        .map(|c| c.cloud.points)
    };
    let started = Instant::now();
    let mut builder = GridBuilder::new(&params);
    for (i, pose) in poses.iter().enumerate().take(MAP_SCANS) {
        builder.add_anchor(pose.translation.vector.into());
        builder.add_points(scan(i)?.iter().map(|p| {
            let v = pose * Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [v.x, v.y, v.z]
        }));
    }
    let grid = builder.finish(&params)?;
    let view = grid.view();
    println!(
        "grid: {:?} voxels of {resolution} m, {} levels, {:.2} MiB, {:.0} ms to build",
        grid.dims,
        grid.levels,
        view.bytes() as f64 / (1 << 20) as f64,
        started.elapsed().as_secs_f64() * 1e3,
    );
    let relocalize = RelocalizeParams::default();
    let mut ranks = Vec::new();
    let mut times = Vec::new();
    for (q, reference) in poses.iter().enumerate().skip(MAP_SCANS) {
        let points = scan(q)?;
        let t0 = Instant::now();
        let proposal = propose(
            &view,
            &points,
            ScanUp::Own(own_up(&points, &relocalize)),
            Columns::All,
            None,
            &relocalize,
        )?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        times.push(ms);
        let rank = proposal.poses.iter().position(|(pose, _)| {
            translation_distance(pose, reference) < RIGHT_M
                && rotation_distance(pose, reference).to_degrees() < RIGHT_DEG
        });
        println!(
            "scan {q}: {} points, {} nodes, {ms:.0} ms, right place at rank {rank:?} of {}",
            proposal.points,
            proposal.nodes,
            proposal.poses.len()
        );
        ranks.push(rank);
    }
    let first = ranks.iter().filter(|r| **r == Some(0)).count();
    let any = ranks.iter().filter(|r| r.is_some()).count();
    times.sort_by(f64::total_cmp);
    println!(
        "right place first: {first} / {}, among the proposals: {any}; search p50 {:.0} ms, max {:.0} ms",
        ranks.len(),
        times[times.len() / 2],
        times.last().copied().unwrap_or(0.0)
    );
    Ok(())
}
