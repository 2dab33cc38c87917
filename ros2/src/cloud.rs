//! Point clouds between ROS 2 and kfmap: a received `PointCloud2` read by the bag
//! decoder's layout rules (every layout `kfmap localize --bag` reads, per-point times
//! included), and the served map written as a positions-only `PointCloud2`.

use kfmap_bag::msg::{PointCloud2 as Layout, PointField as LayoutField};
use kfmap_geometry::cloud::{FilterOptions, PointCloud};

use crate::msgs::{Header, PointCloud2, PointField};

/// `sensor_msgs/PointField` FLOAT32.
const FLOAT32: u8 = 7;

/// Why a received cloud is not localized.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BadCloud {
    /// The layout is not one a point cloud can be read from (no x field, a field past
    /// the point's end, data shorter than the rows...).
    #[error("cannot read the cloud: {0}")]
    Layout(String),
    /// Nothing left after dropping invalid returns (NaN, the origin, too near).
    #[error("the cloud holds no valid point ({0} received)")]
    NoValidPoint(usize),
    /// Thinning failed (a cloud spanning more voxels than can be indexed).
    #[error("cannot thin the cloud: {0}")]
    Thinning(String),
}

/// The points of `msg` as `kfmap localize` reads a bag's cloud: x y z, intensity and
/// per-point time (seconds after the header stamp) when fields give them, invalid
/// returns dropped, then thinned to `voxel` metres (0: every point).
pub fn scan_of(msg: &PointCloud2, voxel: f64) -> Result<PointCloud, BadCloud> {
    let layout = Layout {
        stamp: kfmap_bag::msg::Stamp {
            sec: i64::from(msg.header.stamp.sec),
            nanosec: msg.header.stamp.nanosec,
        },
        frame_id: msg.header.frame_id.clone(),
        height: msg.height,
        width: msg.width,
        fields: msg
            .fields
            .iter()
            .map(|f| LayoutField {
                name: f.name.clone(),
                offset: f.offset,
                datatype: f.datatype,
                count: f.count,
            })
            .collect(),
        is_bigendian: msg.is_bigendian,
        point_step: msg.point_step,
        row_step: msg.row_step,
        data: &msg.data,
        is_dense: msg.is_dense,
    };
    let mut cloud = layout
        .to_cloud()
        .map_err(|e| BadCloud::Layout(e.to_string()))?;
    let received = cloud.len();
    cloud.remove_invalid(FilterOptions::default().min_range);
    if cloud.is_empty() {
        return Err(BadCloud::NoValidPoint(received));
    }
    if voxel > 0.0 {
        cloud = cloud
            .voxel_downsample(voxel)
            .map_err(|e| BadCloud::Thinning(e.to_string()))?;
    }
    Ok(cloud)
}

/// A positions-only `PointCloud2` (x y z FLOAT32, little-endian, one row) of `points`.
pub fn xyz_message(header: Header, points: &[[f32; 3]]) -> PointCloud2 {
    let field = |name: &str, offset: u32| PointField {
        name: name.into(),
        offset,
        datatype: FLOAT32,
        count: 1,
    };
    let mut data = Vec::with_capacity(points.len() * 12);
    for p in points {
        for v in p {
            data.extend_from_slice(&v.to_le_bytes());
        }
    }
    PointCloud2 {
        header,
        height: 1,
        width: points.len() as u32,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        is_bigendian: false,
        point_step: 12,
        row_step: 12 * points.len() as u32,
        data,
        is_dense: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::Time;

    fn header() -> Header {
        Header {
            stamp: Time { sec: 5, nanosec: 0 },
            frame_id: "lidar".into(),
        }
    }

    #[test]
    fn a_written_cloud_reads_back_point_for_point() {
        let points: Vec<[f32; 3]> = (0..50)
            .map(|i| {
                [
                    i as f32 * 0.7 + 1.0,
                    -(i as f32) * 0.3,
                    0.25 * (i % 7) as f32,
                ]
            })
            .collect();
        let msg = xyz_message(header(), &points);
        let back = scan_of(&msg, 0.0).unwrap();
        assert_eq!(back.points, points);
        assert!(back.time.is_none());
    }

    #[test]
    fn bad_clouds_are_refused_by_name() {
        let good = xyz_message(header(), &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let mut no_x = good.clone();
        no_x.fields.retain(|f| f.name != "x");
        assert!(matches!(scan_of(&no_x, 0.0), Err(BadCloud::Layout(m)) if m.contains('x')));
        let mut short = good.clone();
        short.data.truncate(13);
        assert!(matches!(scan_of(&short, 0.0), Err(BadCloud::Layout(_))));
        let empty = xyz_message(header(), &[]);
        assert_eq!(scan_of(&empty, 0.0), Err(BadCloud::NoValidPoint(0)));
        let nan = xyz_message(header(), &[[f32::NAN, 0.0, 1.0], [0.0, 0.0, 0.0]]);
        assert_eq!(scan_of(&nan, 0.0), Err(BadCloud::NoValidPoint(2)));
        let mut huge = good;
        huge.width = u32::MAX;
        huge.height = u32::MAX;
        assert!(matches!(scan_of(&huge, 0.0), Err(BadCloud::Layout(_))));
    }
}
