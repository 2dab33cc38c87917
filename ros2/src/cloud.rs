//! Point clouds between ROS 2 and kfmap: a received `PointCloud2`, decoded by
//! `kfmap_bag`'s decoder, read by its layout rules (every layout `kfmap localize --bag`
//! reads, per-point times included), and the served map written as a positions-only
//! `PointCloud2` with the encoder beside it.

use kfmap_bag::msg::{EncodeError, PointCloud2, PointField, Stamp, encode_point_cloud2};
use kfmap_geometry::cloud::{FilterOptions, PointCloud};

use crate::config::ScansSection;
use crate::raw::CdrSample;

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
/// returns dropped, every return raised by `[scans] vertical-angle-offset-deg`, then
/// thinned to `[scans] voxel` metres (0: every point).
pub fn scan_of(msg: &PointCloud2<'_>, scans: &ScansSection) -> Result<PointCloud, BadCloud> {
    let mut cloud = msg
        .to_cloud()
        .map_err(|e| BadCloud::Layout(e.to_string()))?;
    let received = cloud.len();
    cloud.remove_invalid(FilterOptions::default().min_range);
    if cloud.is_empty() {
        return Err(BadCloud::NoValidPoint(received));
    }
    cloud.raise_elevation(scans.vertical_angle_offset_deg);
    let voxel = scans.voxel;
    if voxel > 0.0 {
        cloud = cloud
            .voxel_downsample(voxel)
            .map_err(|e| BadCloud::Thinning(e.to_string()))?;
    }
    Ok(cloud)
}

/// The x y z bytes of `points` (FLOAT32, little-endian), 12 per point.
fn xyz_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    points
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

/// A positions-only `PointCloud2` (x y z FLOAT32, little-endian, one row) over `data`
/// ([`xyz_bytes`]).
fn xyz_layout<'a>(stamp: Stamp, frame_id: &str, data: &'a [u8]) -> PointCloud2<'a> {
    let field = |name: &str, offset: u32| PointField {
        name: name.into(),
        offset,
        datatype: FLOAT32,
        count: 1,
    };
    let width = (data.len() / 12) as u32;
    PointCloud2 {
        stamp,
        frame_id: frame_id.into(),
        height: 1,
        width,
        fields: vec![field("x", 0), field("y", 4), field("z", 8)],
        is_bigendian: false,
        point_step: 12,
        row_step: 12 * width,
        data,
        is_dense: true,
    }
}

/// `points` as a positions-only `PointCloud2` sample, encoded for the DDS writer.
pub fn xyz_sample(
    stamp: Stamp,
    frame_id: &str,
    points: &[[f32; 3]],
) -> Result<CdrSample, EncodeError> {
    let data = xyz_bytes(points);
    encode_point_cloud2(&xyz_layout(stamp, frame_id, &data)).map(CdrSample)
}

#[cfg(test)]
mod tests {
    use kfmap_bag::Encoding;
    use kfmap_bag::msg::decode_point_cloud2;

    use super::*;

    const STAMP: Stamp = Stamp { sec: 5, nanosec: 7 };

    /// `[scans]` that keeps every point as received.
    fn every_point() -> ScansSection {
        ScansSection {
            voxel: 0.0,
            ..ScansSection::default()
        }
    }

    /// `[scans] vertical-angle-offset-deg` raises every return as bake.toml's does: the
    /// same points raised by `PointCloud::raise_elevation` (whose own test checks it
    /// against the spherical construction), and not left as received.
    #[test]
    fn the_vertical_angle_offset_raises_every_return() {
        let points = vec![[12.0, 3.0, -2.0], [-30.0, -52.0, 1.2], [-6.9, 0.6, -3.1]];
        let sample = xyz_sample(STAMP, "lidar", &points).unwrap();
        let msg = decode_point_cloud2(&sample.0, Encoding::Cdr).unwrap();
        let scans = ScansSection {
            vertical_angle_offset_deg: 0.205,
            ..every_point()
        };
        let raised = scan_of(&msg, &scans).unwrap();
        let mut want = PointCloud::from_points(points.clone());
        want.raise_elevation(0.205);
        assert_eq!(raised.points, want.points);
        assert_ne!(raised.points, points);
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
        let sample = xyz_sample(STAMP, "map", &points).unwrap();
        let msg = decode_point_cloud2(&sample.0, Encoding::Cdr).unwrap();
        assert_eq!((msg.stamp, msg.frame_id.as_str()), (STAMP, "map"));
        let back = scan_of(&msg, &every_point()).unwrap();
        assert_eq!(back.points, points);
        assert!(back.time.is_none());
    }

    #[test]
    fn bad_clouds_are_refused_by_name() {
        let data = xyz_bytes(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let good = xyz_layout(STAMP, "lidar", &data);
        let mut no_x = good.clone();
        no_x.fields.retain(|f| f.name != "x");
        assert!(
            matches!(scan_of(&no_x, &every_point()), Err(BadCloud::Layout(m)) if m.contains('x'))
        );
        let mut short = good.clone();
        short.data = &data[..13];
        assert!(matches!(
            scan_of(&short, &every_point()),
            Err(BadCloud::Layout(_))
        ));
        assert_eq!(
            scan_of(&xyz_layout(STAMP, "lidar", &[]), &every_point()),
            Err(BadCloud::NoValidPoint(0))
        );
        let nan = xyz_bytes(&[[f32::NAN, 0.0, 1.0], [0.0, 0.0, 0.0]]);
        assert_eq!(
            scan_of(&xyz_layout(STAMP, "lidar", &nan), &every_point()),
            Err(BadCloud::NoValidPoint(2))
        );
        let mut huge = good;
        huge.width = u32::MAX;
        huge.height = u32::MAX;
        assert!(matches!(
            scan_of(&huge, &every_point()),
            Err(BadCloud::Layout(_))
        ));
        // A stamp past ROS 2's int32 seconds is not written.
        let late = Stamp {
            sec: i64::from(i32::MAX) + 1,
            nanosec: 0,
        };
        assert_eq!(
            xyz_sample(late, "map", &[[1.0, 2.0, 3.0]]),
            Err(EncodeError::Stamp(late.sec))
        );
    }
}
