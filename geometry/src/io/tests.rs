use super::*;
use kfmap_testdata::Scratch;

fn sample_cloud(with_attributes: bool) -> PointCloud {
    let points: Vec<[f32; 3]> = (0..500)
        .map(|i| {
            let t = i as f32 * 0.1;
            [t.cos() * 10.0, t.sin() * 10.0, (t * 0.3).sin() - 1.5]
        })
        .collect();
    let mut cloud = PointCloud::from_points(points);
    if with_attributes {
        let n = cloud.len();
        cloud.view_dirs = Some(
            cloud
                .points
                .iter()
                .map(|p| {
                    let norm = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                    [-p[0] / norm, -p[1] / norm, -p[2] / norm]
                })
                .collect(),
        );
        cloud.intensity = Some((0..n).map(|i| (i % 256) as f32).collect());
        cloud.time = Some((0..n).map(|i| i as f32 * 1e-4).collect());
    }
    cloud
}

#[test]
fn every_writer_round_trips_through_its_reader() {
    let dir = Scratch::new("io-round-trip");
    let formats = [
        (CloudFormat::Pcd(PcdData::Ascii), "a.pcd", true),
        (CloudFormat::Pcd(PcdData::Binary), "b.pcd", true),
        // Positions alone: written by their own path.
        (CloudFormat::Pcd(PcdData::Binary), "xyz.pcd", false),
        (CloudFormat::Pcd(PcdData::BinaryCompressed), "c.pcd", true),
        (CloudFormat::Ply(PlyEncoding::Ascii), "a.ply", true),
        (
            CloudFormat::Ply(PlyEncoding::BinaryLittleEndian),
            "b.ply",
            true,
        ),
        (CloudFormat::Bin(BinLayout::Xyz), "raw.bin", false),
    ];
    let options = ReadOptions {
        bin_layout: Some(BinLayout::Xyz),
        ..ReadOptions::default()
    };
    for (format, name, attrs) in formats {
        let cloud = sample_cloud(attrs);
        let path = dir.file(name);
        write_cloud(&path, &cloud, format).unwrap();
        let back = read_cloud(&path, &options).unwrap();
        assert_eq!(back.format, format);
        assert_eq!(back.filter.unwrap().dropped(), 0);
        // Text formats print shortest round-trip floats, so every format is exact.
        assert_eq!(back.cloud, cloud, "{format}");
    }
    let mut kitti = sample_cloud(false);
    kitti.intensity = Some((0..kitti.len()).map(|i| i as f32 * 0.5).collect());
    let path = dir.file("k.bin");
    write_cloud(&path, &kitti, CloudFormat::Bin(BinLayout::Xyzi)).unwrap();
    assert_eq!(
        read_cloud(&path, &ReadOptions::default()).unwrap().cloud,
        kitti
    );
}

#[test]
fn sidecar_selects_the_bin_layout() {
    let dir = Scratch::new("io-sidecar");
    let cloud = sample_cloud(false);
    let path = dir.file("side.bin");
    std::fs::write(&path, write_bin(&cloud, BinLayout::Xyz)).unwrap();
    std::fs::write(dir.file("side.bin.layout"), "xyz\n").unwrap();
    let back = read_cloud(&path, &ReadOptions::default()).unwrap();
    assert_eq!(back.format, CloudFormat::Bin(BinLayout::Xyz));
    assert_eq!(back.cloud.points, cloud.points);
}

#[test]
fn truncated_and_malformed_files_are_errors_naming_the_place() {
    let dir = Scratch::new("io-malformed");
    let cloud = sample_cloud(true);
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("trunc.pcd", { let b = write_pcd(&cloud, PcdData::Binary); b[..b.len() - 7].to_vec() }, "truncated"),
        ("trunc_c.pcd", { let b = write_pcd(&cloud, PcdData::BinaryCompressed); b[..b.len() - 30].to_vec() }, "truncated"),
        ("trunc_a.pcd", { let b = write_pcd(&cloud, PcdData::Ascii); b[..b.len() / 2].to_vec() }, "line"),
        ("trunc.ply", { let b = write_ply(&cloud, PlyEncoding::BinaryLittleEndian); b[..b.len() - 3].to_vec() }, "byte"),
        ("nofields.pcd", b"VERSION 0.7\nPOINTS 1\nDATA ascii\n1 2 3\n".to_vec(), "line 3"),
        ("badnum.pcd", b"FIELDS x y z\nPOINTS 2\nDATA ascii\n1 2 3\n1 two 3\n".to_vec(), "line 5"),
        ("noz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n".to_vec(), "no field 'z'"),
        ("big.ply", b"ply\nformat binary_big_endian 1.0\nend_header\n".to_vec(), "line 2"),
        ("odd.bin", vec![0u8; 17], "byte 16"),
        ("liar.pcd", b"FIELDS x y z\nPOINTS 1000000000000000\nDATA binary\n\0\0\0\0".to_vec(), "truncated"),
    ];
    for (name, bytes, expect) in cases {
        let path = dir.file(name);
        std::fs::write(&path, &bytes).unwrap();
        let err = read_cloud(&path, &ReadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains(name) && err.contains(expect), "{name}: {err}");
    }
    let err = read_cloud(&dir.file("missing.pcd"), &ReadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing.pcd"), "{err}");
}

#[test]
fn pcd_reader_handles_mixed_types_counts_and_field_order() {
    // Fields in an unusual order with a U8 field of COUNT 2 between them.
    let mut body = Vec::new();
    for i in 0..3u8 {
        body.extend_from_slice(&(i as f64 * 2.0).to_le_bytes()); // z as F8
        body.extend_from_slice(&[i, 7]); // rgb-ish U1 x2
        body.extend_from_slice(&(i as f32).to_le_bytes()); // x
        body.extend_from_slice(&(-(i as i16)).to_le_bytes()); // y as I2
    }
    let mut bytes = b"# .PCD v0.7\nVERSION 0.7\nFIELDS z c x y\nSIZE 8 1 4 2\nTYPE F U F I\nCOUNT 1 2 1 1\nWIDTH 3\nHEIGHT 1\nPOINTS 3\nDATA binary\n".to_vec();
    bytes.extend(body);
    let (cloud, data, fields) = read_pcd(Path::new("mixed.pcd"), &bytes).unwrap();
    assert_eq!(data, PcdData::Binary);
    assert_eq!(fields, vec!["z", "c", "c_1", "x", "y"]);
    assert_eq!(
        cloud.points,
        vec![[0.0, 0.0, 0.0], [1.0, -1.0, 2.0], [2.0, -2.0, 4.0]]
    );
}

#[test]
fn filter_is_applied_on_load_and_reported() {
    let dir = Scratch::new("io-filter");
    let mut cloud = sample_cloud(false);
    cloud.points[3] = [0.0; 3];
    cloud.points[7] = [0.01, 0.0, 0.0];
    let path = dir.file("filtered.pcd");
    write_cloud(&path, &cloud, CloudFormat::Pcd(PcdData::Binary)).unwrap();
    let loaded = read_cloud(&path, &ReadOptions::default()).unwrap();
    let report = loaded.filter.unwrap();
    assert_eq!(
        (report.at_origin, report.too_close, report.kept),
        (1, 1, 498)
    );
    assert_eq!(loaded.points_in_file, 500);
    let raw = ReadOptions {
        filter: FilterOptions {
            enabled: false,
            ..FilterOptions::default()
        },
        ..ReadOptions::default()
    };
    assert_eq!(read_cloud(&path, &raw).unwrap().cloud.len(), 500);
}

/// Fuzzing (`fuzz/regressions/pcd_width_height_overflow.pcd`): WIDTH x HEIGHT without a
/// POINTS line overflowed (a panic with overflow checks, a wrong count without).
#[test]
fn pcd_width_times_height_overflow_is_an_error() {
    let bytes = b"FIELDS x\nWIDTH 2\nHEIGHT 9223372036854775808\nDATA ascii\n";
    let e = read_pcd(Path::new("wh.pcd"), bytes).unwrap_err();
    assert!(e.to_string().contains("WIDTH x HEIGHT"), "{e}");
}

/// Fuzzing (`fuzz/regressions/pcd_count_allocation.pcd`): a COUNT of 10^12 in a
/// 60-byte file allocated a name per value and exhausted memory.
#[test]
fn pcd_count_is_bounded_before_allocating() {
    let bytes = b"FIELDS x y z\nCOUNT 1 1 1000000000000\nPOINTS 0\nDATA binary\n";
    let e = read_pcd(Path::new("count.pcd"), bytes).unwrap_err();
    assert!(e.to_string().contains("COUNT"), "{e}");
    let overflow = b"FIELDS x y\nCOUNT 18446744073709551615 2\nPOINTS 0\nDATA ascii\n";
    assert!(read_pcd(Path::new("sum.pcd"), overflow).is_err());
    // A wide descriptor (VFH: 308 values) still reads.
    let vfh = b"FIELDS x y z vfh\nCOUNT 1 1 1 308\nPOINTS 0\nDATA ascii\n";
    assert!(read_pcd(Path::new("vfh.pcd"), vfh).is_ok());
}
