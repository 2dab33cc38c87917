//! How often a Scan Context finds the right place on real data (issue 21's descriptor
//! choice): `../shared/data/balm_os0`, map of scans 0-115, each of scans 116-176 (a
//! revisit 2.3-4 m off the first pass) compared with every map scan. Scans are levelled
//! with their reference roll and pitch (what an IMU's gravity gives); a candidate is the
//! right place when its reference position is within 5 m of the query's.
//!
//! ```sh
//! cargo run --release -p kfmap-shared --example place_recall [SENSOR_HEIGHT] [MAX_RANGE]
//! ```

use kfmap_shared::datasets::shared_data_dir;
use kfmap_shared::io::{ReadOptions, read_cloud, read_trajectory};
use kfmap_shared::place::{ScanContext, ScanContextParams};
use nalgebra::{UnitQuaternion, Vector3};

const MAP_SCANS: usize = 116;
const RIGHT_PLACE_M: f64 = 5.0;
const TOP: [usize; 4] = [1, 5, 10, 20];

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
    let mut found = [0usize; TOP.len()];
    let queries = MAP_SCANS..poses.len();
    for q in queries.clone() {
        let mut ranked: Vec<(f64, usize)> = (0..MAP_SCANS)
            .filter_map(|m| Some((descriptors[q].compare(&descriptors[m])?.distance, m)))
            .collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (slot, &k) in TOP.iter().enumerate() {
            let right = ranked[..k]
                .iter()
                .any(|&(_, m)| (position(q) - position(m)).norm() < RIGHT_PLACE_M);
            found[slot] += usize::from(right);
        }
    }
    println!(
        "sensor height {} m, max range {} m: right place within the best 1 / 5 / 10 / 20 of {} queries: {} / {} / {} / {}",
        params.sensor_height,
        params.max_range,
        queries.len(),
        found[0],
        found[1],
        found[2],
        found[3]
    );
    Ok(())
}
