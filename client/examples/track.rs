//! Track a folder of scans against a running `kfmap serve`, starting with no pose guess:
//! the first scan is relocalized, every next one tracked (the README's Rust example).
//!
//! `cargo run --release -p kfmap-client --example track -- MAP_NAME SCAN_DIR`

use kfmap_client::{Client, ClientOptions, Tracker, TrackerOptions};
use kfmap_geometry::io::{ReadOptions, read_cloud};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, map_name, scan_dir] = &args[..] else {
        return Err("usage: track MAP_NAME SCAN_DIR".into());
    };
    let mut client = Client::connect(map_name, ClientOptions::default())?;
    let mut tracker = Tracker::relocalizing(TrackerOptions::default());
    let mut scans: Vec<_> = std::fs::read_dir(scan_dir)?.collect::<Result<_, _>>()?;
    scans.sort_by_key(|entry| entry.path());
    for (i, entry) in scans.iter().enumerate() {
        let scan = read_cloud(&entry.path(), &ReadOptions::default())?.cloud;
        let tracked =
            tracker.track_cloud(&mut client, &scan.voxel_downsample(0.25)?, i as f64 * 0.1)?;
        let health = &tracked.localized.health;
        let at = tracked.localized.pose.translation.vector;
        println!(
            "{i}: {:?} at {at:.2?}, {:.0} % paired",
            health.status,
            100.0 * health.inlier_ratio
        );
    }
    Ok(())
}
