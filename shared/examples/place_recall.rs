//! How often a Scan Context finds the right place on real data (issue 21's descriptor
//! choice): `../shared/data/balm_os0`, map of scans 0-115, each of scans 116-176 (a
//! revisit 2.3-4 m off the first pass) compared with every map scan. Scans are levelled
//! with their reference roll and pitch (what an IMU's gravity gives); a candidate is the
//! right place when its reference position is within 5 m of the query's. Second,
//! the same queries against views of the merged map (scans 0-115 at their poses, 0.1 m
//! voxels) from virtual positions every `GRID_M` metres around the map's keyframes,
//! levelled at yaw 0: a descriptor per position instead of per scan, which tolerates
//! the revisit's offset from the first pass. With `occlude`, a view keeps only the
//! nearest map point along each beam, as a scan from there would.
//!
//! ```sh
//! cargo run --release -p kfmap-shared --example place_recall [SENSOR_HEIGHT] [MAX_RANGE] [occlude]
//! ```

use kfmap_shared::cloud::PointCloud;
use kfmap_shared::datasets::shared_data_dir;
use kfmap_shared::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_shared::place::{ScanContext, ScanContextParams};
use nalgebra::{UnitQuaternion, Vector3};

const MAP_SCANS: usize = 116;
const RIGHT_PLACE_M: f64 = 5.0;
const TOP: [usize; 4] = [1, 5, 10, 20];
/// Spacing of the virtual positions, metres.
const GRID_M: f64 = 1.0;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let Some(data) = shared_data_dir() else {
        println!("../shared/data is not beside this checkout: nothing to measure");
        return Ok(());
    };
    let dir = data.join("balm_os0");
    let mut args = std::env::args().skip(1);
    let params = ScanContextParams {
        sensor_height: args.next().map_or(Ok(1.5), |s| s.parse())?,
        max_range: args.next().map_or(Ok(40.0), |s| s.parse())?,
        ..Default::default()
    };
    params.validate()?;
    // "occlude": a view keeps only the nearest point along each beam, as a scan would.
    let occlude = args.next().is_some_and(|a| a == "occlude");
    let poses = read_trajectory(&dir.join("poses.txt"))?.poses;
    let mut descriptors = Vec::with_capacity(poses.len());
    for (i, pose) in poses.iter().enumerate() {
        let path = dir.join(format!("scans/{i:06}.pcd"));
        let cloud = read_cloud(&path, &ReadOptions::default())?.cloud;
        let (_, _, yaw) = pose.rotation.euler_angles();
        let level = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -yaw) * pose.rotation;
        let points: Vec<[f32; 3]> = cloud
            .points
            .iter()
            .map(|p| {
                let v = level * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect();
        descriptors.push(ScanContext::of_points(&points, params));
    }
    let position = |i: usize| poses[i].translation.vector;
    let queries = MAP_SCANS..poses.len();
    let by_scan = recall(
        queries.clone(),
        &descriptors,
        |q, m| (position(q) - position(m)).norm() < RIGHT_PLACE_M,
        MAP_SCANS,
    );
    report("map scans", &params, queries.len(), by_scan);

    // The merged map, and views of it from virtual positions near the keyframes.
    let mut merged = Vec::new();
    for (i, pose) in poses.iter().enumerate().take(MAP_SCANS) {
        let path = dir.join(format!("scans/{i:06}.pcd"));
        let cloud = read_cloud(&path, &ReadOptions::default())?.cloud;
        merged.extend(cloud.points.iter().map(|p| {
            let v = pose * nalgebra::Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            [v.x as f32, v.y as f32, v.z as f32]
        }));
    }
    let merged = PointCloud::from_points(merged)
        .voxel_downsample(0.1)?
        .points;
    let mut sites: Vec<Vector3<f64>> = Vec::new();
    for m in 0..MAP_SCANS {
        let p = position(m);
        let snapped = Vector3::new(
            (p.x / GRID_M).round() * GRID_M,
            (p.y / GRID_M).round() * GRID_M,
            p.z,
        );
        for dx in -3..=3 {
            for dy in -3..=3 {
                let site =
                    snapped + Vector3::new(f64::from(dx) * GRID_M, f64::from(dy) * GRID_M, 0.0);
                if !sites.iter().any(|s| (s.xy() - site.xy()).norm() < 1e-6) {
                    sites.push(site);
                }
            }
        }
    }
    let views: Vec<ScanContext> = sites
        .iter()
        .map(|site| {
            let local: Vec<[f32; 3]> = merged
                .iter()
                .map(|p| {
                    [
                        p[0] - site.x as f32,
                        p[1] - site.y as f32,
                        p[2] - site.z as f32,
                    ]
                })
                .collect();
            let local = if occlude { visible(&local) } else { local };
            ScanContext::of_points(&local, params)
        })
        .collect();
    let mut all = views;
    let first_query = all.len();
    all.extend(queries.clone().map(|q| descriptors[q].clone()));
    let by_view = recall(
        first_query..all.len(),
        &all,
        |q, v| (position(q - first_query + MAP_SCANS).xy() - sites[v].xy()).norm() < RIGHT_PLACE_M,
        first_query,
    );
    report(
        &format!(
            "{} {}",
            sites.len(),
            if occlude {
                "occluded map views"
            } else {
                "map views"
            }
        ),
        &params,
        queries.len(),
        by_view,
    );
    Ok(())
}

/// The points a 360 x 90 deg LiDAR at the origin would see: the nearest per beam of
/// 0.5 deg azimuth x 1 deg elevation.
fn visible(points: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let mut nearest: std::collections::HashMap<(i32, i32), (f32, [f32; 3])> =
        std::collections::HashMap::new();
    for p in points {
        let range = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        if range < 0.3 {
            continue;
        }
        let azimuth = p[1].atan2(p[0]).to_degrees();
        let elevation = (p[2] / range).asin().to_degrees();
        let beam = ((azimuth * 2.0).floor() as i32, elevation.floor() as i32);
        let slot = nearest.entry(beam).or_insert((f32::INFINITY, *p));
        if range < slot.0 {
            *slot = (range, *p);
        }
    }
    nearest.into_values().map(|(_, p)| p).collect()
}

/// For each query, whether a right candidate is among the best `TOP` of
/// `descriptors[..candidates]`.
fn recall(
    queries: std::ops::Range<usize>,
    descriptors: &[ScanContext],
    right: impl Fn(usize, usize) -> bool,
    candidates: usize,
) -> [usize; TOP.len()] {
    let mut found = [0usize; TOP.len()];
    for q in queries {
        let mut ranked: Vec<(f64, usize)> = (0..candidates)
            .filter_map(|m| Some((descriptors[q].compare(&descriptors[m])?.distance, m)))
            .collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (slot, &k) in TOP.iter().enumerate() {
            found[slot] += usize::from(ranked[..k].iter().any(|&(_, m)| right(q, m)));
        }
    }
    found
}

fn report(against: &str, params: &ScanContextParams, queries: usize, found: [usize; TOP.len()]) {
    println!(
        "against {against}, sensor height {} m, max range {} m: right place within the best 1 / 5 / 10 / 20 of {queries} queries: {} / {} / {} / {}",
        params.sensor_height, params.max_range, found[0], found[1], found[2], found[3]
    );
}
