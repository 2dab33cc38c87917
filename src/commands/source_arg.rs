//! `--dataset DIR` or `--bag PATH --points-topic TOPIC [--imu-topic TOPIC]`: where a
//! command reads its scans (and IMU) from, shared by `bake` and `localize`.

use std::path::PathBuf;

use kfmap_bake::source::{BagSource, Source};

/// Where the scans come from.
#[derive(clap::Args, Debug, Clone)]
pub struct SourceArgs {
    /// Dataset folder: scan files (DIR/scans/ or DIR), a pose file and imu.csv beside.
    #[arg(
        long,
        value_name = "DIR",
        required_unless_present = "bag",
        conflicts_with = "bag"
    )]
    pub dataset: Option<PathBuf>,
    /// A bag instead of a folder: MCAP (.mcap), rosbag2 sqlite3 (.db3 or its folder with
    /// metadata.yaml) or ROS 1 (.bag v2.0); `kfmap inspect-bag` lists its topics.
    #[arg(long, value_name = "PATH", requires = "points_topic")]
    pub bag: Option<PathBuf>,
    /// With --bag: the sensor_msgs/PointCloud2 topic whose clouds are the scans (scan
    /// time = each cloud's header stamp; per-point times from the driver's field).
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    pub points_topic: Option<String>,
    /// With --bag: the sensor_msgs/Imu topic (gravity, gyro-aided odometry), on the
    /// clouds' header clock.
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    pub imu_topic: Option<String>,
}

impl SourceArgs {
    /// The source the flags name (clap has checked that one of the two is given).
    pub fn source(&self) -> Source {
        match (&self.dataset, &self.bag) {
            (_, Some(bag)) => Source::Bag(BagSource {
                path: bag.clone(),
                points_topic: self.points_topic.clone().unwrap_or_default(),
                imu_topic: self.imu_topic.clone(),
            }),
            (Some(dir), None) => Source::Folder(dir.clone()),
            (None, None) => unreachable!("clap requires --dataset or --bag"),
        }
    }
}
