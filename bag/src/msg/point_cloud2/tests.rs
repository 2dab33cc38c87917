//! Unit tests of PointCloud2 decoding on hand-built messages (the integration tests in
//! `bag/tests/messages.rs` check against an independent serializer).

use proptest::prelude::*;

use super::super::writer::Writer;
use super::*;

/// A field of a hand-built cloud: name, offset, datatype code.
type F = (&'static str, u32, u8);

/// Serializes a PointCloud2 with `fields` (count 1 each) and raw `data`.
#[allow(clippy::too_many_arguments)]
fn cloud_bytes(
    encoding: Encoding,
    cdr_big_endian: bool,
    stamp: (i32, u32),
    (height, width): (u32, u32),
    fields: &[F],
    is_bigendian: bool,
    (point_step, row_step): (u32, u32),
    data: &[u8],
) -> Vec<u8> {
    let mut w = Writer::new(encoding, cdr_big_endian);
    w.header(stamp.0, stamp.1, "lidar");
    w.u32(height);
    w.u32(width);
    w.u32(fields.len() as u32);
    for &(name, offset, datatype) in fields {
        w.string(name);
        w.u32(offset);
        w.u8(datatype);
        w.u32(1);
    }
    w.u8(is_bigendian.into());
    w.u32(point_step);
    w.u32(row_step);
    w.bytes(data);
    w.u8(1);
    w.out
}

/// Points of `x y z intensity(u16) t(u32)` packed into 18 bytes, in either byte order.
fn packed_points(points: &[([f32; 3], u16, u32)], big_endian: bool) -> Vec<u8> {
    let mut data = Vec::new();
    for &(xyz, i, t) in points {
        for c in xyz {
            data.extend(if big_endian {
                c.to_be_bytes()
            } else {
                c.to_le_bytes()
            });
        }
        data.extend(if big_endian {
            i.to_be_bytes()
        } else {
            i.to_le_bytes()
        });
        data.extend(if big_endian {
            t.to_be_bytes()
        } else {
            t.to_le_bytes()
        });
    }
    data
}

const PACKED: [F; 5] = [
    ("x", 0, 7),
    ("y", 4, 7),
    ("z", 8, 7),
    ("intensity", 12, 4),
    ("t", 14, 6),
];

const POINTS: [([f32; 3], u16, u32); 3] = [
    ([1.0, -2.0, 3.5], 10, 0),
    ([f32::NAN, 0.0, 0.0], 0, 50_000_000),
    ([0.0, 0.0, 0.0], 65535, 99_999_999),
];

#[test]
fn decodes_each_serialization_and_point_byte_order() {
    for (encoding, cdr_be) in [
        (Encoding::Cdr, false),
        (Encoding::Cdr, true),
        (Encoding::Ros1, false),
    ] {
        for points_be in [false, true] {
            let data = packed_points(&POINTS, points_be);
            let bytes = cloud_bytes(
                encoding,
                cdr_be,
                (100, 5),
                (1, 3),
                &PACKED,
                points_be,
                (18, 54),
                &data,
            );
            let msg = decode_point_cloud2(&bytes, encoding).unwrap();
            assert_eq!(msg.frame_id, "lidar");
            assert_eq!(
                msg.stamp,
                Stamp {
                    sec: 100,
                    nanosec: 5
                }
            );
            assert_eq!(msg.len(), 3);
            assert_eq!(msg.data, &data[..], "the data is borrowed as is");
            let time = msg.time_field().unwrap();
            assert_eq!(time.unit, TimeUnit::RelativeNanos);
            let cloud = msg.to_cloud().unwrap();
            assert_eq!(cloud.points[0], [1.0, -2.0, 3.5]);
            assert!(cloud.points[1][0].is_nan(), "NaN returns are kept");
            assert_eq!(cloud.points[2], [0.0; 3], "zero returns are kept");
            assert_eq!(cloud.intensity.unwrap(), [10.0, 0.0, 65535.0]);
            assert_eq!(
                cloud.time.unwrap(),
                [0.0, 0.05, (99_999_999.0 * 1e-9) as f32]
            );
        }
    }
}

#[test]
fn rows_are_read_with_row_step_skipping_padding() {
    // 2 rows of 2 points, 4 bytes of padding after each row.
    let pts: Vec<_> = (0..4)
        .map(|i| ([i as f32, 0.0, 0.0], i as u16, 0))
        .collect();
    let mut data = Vec::new();
    for row in pts.chunks(2) {
        data.extend(packed_points(row, false));
        data.extend([0xEE; 4]);
    }
    let bytes = cloud_bytes(
        Encoding::Cdr,
        false,
        (0, 0),
        (2, 2),
        &PACKED,
        false,
        (18, 40),
        &data,
    );
    let cloud = decode_point_cloud2(&bytes, Encoding::Cdr)
        .unwrap()
        .to_cloud()
        .unwrap();
    let xs: Vec<f32> = cloud.points.iter().map(|p| p[0]).collect();
    assert_eq!(xs, [0.0, 1.0, 2.0, 3.0]);
}

#[test]
fn layout_errors_name_the_problem() {
    let data = packed_points(&POINTS, false);
    let err = |fields: &[F], steps: (u32, u32), data: &[u8]| {
        let bytes = cloud_bytes(
            Encoding::Ros1,
            false,
            (0, 0),
            (1, 3),
            fields,
            false,
            steps,
            data,
        );
        match decode_point_cloud2(&bytes, Encoding::Ros1).unwrap_err() {
            DecodeError::Layout(why) => why,
            other => panic!("not a layout error: {other:?}"),
        }
    };
    let e = err(&PACKED[..2], (18, 54), &data);
    assert_eq!(e, "cloud has no field 'z' (fields: x y)");
    let e = err(&[("x", 0, 7), ("y", 4, 7), ("z", 8, 4)], (18, 54), &data);
    assert!(e.contains("'z' is UINT16"), "{e}");
    let e = err(
        &[("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7)],
        (18, 54),
        &data,
    );
    assert_eq!(
        e,
        "field 'intensity' at offset 16 (4 bytes) runs past point_step 18"
    );
    let e = err(&[("x", 0, 7), ("y", 4, 7), ("z", 8, 9)], (18, 54), &data);
    assert!(e.contains("unknown datatype 9"), "{e}");
    let e = err(&PACKED, (18, 53), &data);
    assert_eq!(e, "row_step 53 is less than width 3 x point_step 18 = 54");
    let e = err(&PACKED, (18, 54), &data[..53]);
    assert_eq!(
        e,
        "data holds 53 bytes, fewer than height 1 x row_step 54 = 54"
    );
}

#[test]
fn a_hand_built_cloud_with_a_bad_layout_fails_to_convert_without_panicking() {
    let cloud = PointCloud2 {
        stamp: Stamp::default(),
        frame_id: String::new(),
        height: 3,
        width: 5,
        fields: vec![],
        is_bigendian: false,
        point_step: 0,
        row_step: 0,
        data: &[],
        is_dense: false,
    };
    assert!(cloud.to_cloud().is_err());
    assert_eq!(cloud.time_field(), None);
}

#[test]
fn time_units_follow_magnitude_then_the_stamp() {
    use TimeUnit::*;
    let epoch = Stamp {
        sec: 1_700_000_000,
        nanosec: 500_000_000,
    };
    assert_eq!(infer_time_unit(0.05, epoch), RelativeSeconds);
    assert_eq!(infer_time_unit(-0.09, epoch), RelativeSeconds);
    assert_eq!(infer_time_unit(1_700_000_000.55, epoch), AbsoluteSeconds);
    assert_eq!(infer_time_unit(1.700_000_000_55e18, epoch), AbsoluteNanos);
    // Clocks that count from power-on: the stamp decides.
    let uptime = Stamp {
        sec: 3_600,
        nanosec: 0,
    };
    assert_eq!(infer_time_unit(3.600_05e12, uptime), AbsoluteNanos);
    assert_eq!(infer_time_unit(3_600.05, uptime), AbsoluteSeconds);
    // A stamp near zero (simulators): small values stay relative.
    let zero = Stamp::default();
    assert_eq!(infer_time_unit(0.05, zero), RelativeSeconds);
    // Nothing plausible: the magnitude rule stands.
    assert_eq!(infer_time_unit(1.0e12, zero), AbsoluteSeconds);
    assert_eq!(infer_time_unit(1.0e9, epoch), AbsoluteSeconds);
}

#[test]
fn time_field_names_and_priority() {
    let with = |fields: &[F]| {
        let bytes = cloud_bytes(
            Encoding::Cdr,
            false,
            (0, 0),
            (1, 1),
            fields,
            false,
            (32, 32),
            &[0; 32],
        );
        let msg = decode_point_cloud2(&bytes, Encoding::Cdr).unwrap();
        msg.time_field()
    };
    let xyz = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)];
    let mut livox = xyz.to_vec();
    livox.extend([("timestamp", 16, 8), ("offset_time", 24, 6)]);
    assert_eq!(
        with(&livox),
        Some(TimeField {
            name: "offset_time".into(),
            unit: TimeUnit::RelativeNanos
        })
    );
    let mut velodyne = xyz.to_vec();
    velodyne.push(("time", 12, 7));
    assert_eq!(with(&velodyne).unwrap().unit, TimeUnit::RelativeSeconds);
    assert_eq!(with(&xyz), None);
    assert_eq!(datatype_name(7), "FLOAT32");
    assert_eq!(datatype_name(0), "unknown");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Any corruption of a valid message decodes to a cloud that converts, or fails
    /// with an error; it never panics.
    #[test]
    fn corrupted_messages_never_panic(
        encoding_cdr in any::<bool>(),
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
        cut in any::<prop::sample::Index>(),
    ) {
        let encoding = if encoding_cdr { Encoding::Cdr } else { Encoding::Ros1 };
        let data = packed_points(&POINTS, false);
        let mut bytes = cloud_bytes(encoding, false, (1, 2), (1, 3), &PACKED, false, (18, 54), &data);
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        let cut = cut.index(bytes.len() + 1);
        if let Ok(msg) = decode_point_cloud2(&bytes[..cut], encoding) {
            let _ = msg.time_field();
            let cloud = msg.to_cloud().expect("a decoded cloud converts");
            prop_assert_eq!(cloud.points.len(), msg.len());
            prop_assert!(cloud.validate().is_ok() || cloud.points.iter().flatten().any(|c| !c.is_finite()));
        }
    }
}
