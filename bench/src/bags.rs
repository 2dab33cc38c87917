//! The table's bag rows: reading PointCloud2 clouds from an MCAP file (the payload
//! streamed, then decoded to points), and what baking from a bag costs against baking
//! the same scans from their files. Also `kfmap bench bag-read FILE`, which the
//! rosbags anchor script runs on the file it wrote.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use kfmap_bag::Bag;
use kfmap_bag::msg::decode_point_cloud2;
use kfmap_bake::config::BakeConfig;
use kfmap_bake::dataset::find_scans;
use kfmap_bake::pipeline::{BakeInput, BakeOutput, bake};
use kfmap_bake::scan_range::ScanRange;
use kfmap_bake::source::{BagSource, Source};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::io::{ReadOptions, read_cloud};

use super::anchors::{ROSBAGS_MCAP_READ, ROSBAGS_MCAP_READ_SCRIPT};
use super::table::{Table, anchor};

/// Points of a generated Ouster-like cloud (OS1-128 at 1024 columns).
const CLOUD_POINTS: usize = 131_072;
/// Bytes per point of that layout (ouster-ros: x y z, pad, intensity, t, ...).
const POINT_STEP: usize = 48;

/// Measures the bag rows.
pub(super) fn measure(table: &mut Table, data: Option<&Path>, dir: &Path) -> anyhow::Result<()> {
    table.stage("bag reading");
    let clouds = if table.quick { 8 } else { 40 };
    let file = dir.join(format!("kfmap-bench-{}.mcap", std::process::id()));
    write_ouster_mcap(&file, clouds)?;
    let result = read_rows(table, &file, clouds);
    let _ = std::fs::remove_file(&file);
    result?;
    let Some(balm) = data.map(|d| d.join("balm_os0")).filter(|d| d.is_dir()) else {
        table.skip("bake from a bag vs from files: needs ../shared/data/balm_os0");
        return Ok(());
    };
    bake_rows(table, &balm, dir)
}

/// Streaming and decoding throughput on `file`, one thread.
fn read_rows(table: &mut Table, file: &Path, clouds: usize) -> anyhow::Result<()> {
    let payload = (clouds * CLOUD_POINTS * POINT_STEP) as f64;
    let label =
        format!("MCAP, {clouds} Ouster-layout clouds x {CLOUD_POINTS} points, page cache warm");
    let rows = [
        ("bag read: PointCloud2 messages streamed", false),
        ("bag read: streamed and decoded to points", true),
    ];
    for (k, (name, decode)) in rows.into_iter().enumerate() {
        let ms = table.time_ms(1, || stream(file, decode).expect("read the bag"))?;
        table.push(name, &label, 1, payload / ms / 1e6, "GB/s");
        // The anchor read the full run's file (40 clouds); --quick's is smaller.
        table.anchored(
            (!table.quick)
                .then(|| {
                    anchor(
                        "rosbags 0.11 (Python)",
                        ROSBAGS_MCAP_READ[k],
                        ROSBAGS_MCAP_READ_SCRIPT,
                    )
                })
                .flatten(),
        );
    }
    Ok(())
}

/// Streams every PointCloud2 of the bag; with `decode`, turns each into points. Returns
/// the payload bytes (or points) seen, so the work cannot be optimized away.
fn stream(file: &Path, decode: bool) -> anyhow::Result<usize> {
    let bag = Bag::open(file)?;
    let mut seen = 0;
    for topic in bag.topics().iter().filter(|t| t.is_point_cloud()) {
        for message in bag.messages(topic)? {
            let message = message?;
            if decode {
                let cloud = decode_point_cloud2(&message.data, topic.encoding)?;
                seen += cloud.to_cloud()?.len();
            } else {
                seen += message.data.len();
            }
        }
    }
    Ok(seen)
}

/// `kfmap bench bag-read FILE`: seconds and GB/s to stream, then decode, every
/// PointCloud2 of a bag (best of three), as one JSON line.
pub(super) fn run_read(file: &Path) -> anyhow::Result<()> {
    let best = |decode: bool| -> anyhow::Result<(f64, usize)> {
        let mut best = (f64::INFINITY, 0);
        for _ in 0..3 {
            let started = Instant::now();
            let seen = stream(file, decode)?;
            best = (best.0.min(started.elapsed().as_secs_f64()), seen);
        }
        Ok(best)
    };
    let (stream_s, bytes) = best(false)?;
    let (decode_s, points) = best(true)?;
    let out = serde_json::json!({
        "file": file, "payload_bytes": bytes, "points": points,
        "stream_s": stream_s, "stream_gb_s": bytes as f64 / stream_s / 1e9,
        "decode_s": decode_s, "decode_gb_s": bytes as f64 / decode_s / 1e9,
    });
    println!("{out}");
    Ok(())
}

/// Bakes balm_os0 scans 0-59 at their poses from the scan files and from an MCAP of
/// the same clouds, side by side.
fn bake_rows(table: &mut Table, balm: &Path, dir: &Path) -> anyhow::Result<()> {
    let scans: ScanRange = "0..60".parse().expect("a range");
    let bag = dir.join(format!("kfmap-bench-balm-{}.mcap", std::process::id()));
    let files = find_scans(balm)?;
    let poses = balm.join("poses.txt");
    write_clouds_mcap(&bag, &files[..60], &poses)?;
    // The bag holds 60 clouds: its pose file the first 60 lines.
    let bag_poses = dir.join(format!("kfmap-bench-balm-{}.tum", std::process::id()));
    let text = std::fs::read_to_string(&poses)?;
    let first: Vec<&str> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .take(60)
        .collect();
    std::fs::write(&bag_poses, first.join("\n") + "\n")?;
    let folder = BakeInput {
        poses: Some(poses.clone()),
        scans,
        ..BakeInput::dataset(balm)
    };
    let from_bag = BakeInput {
        source: Source::Bag(BagSource {
            path: bag.clone(),
            points_topic: "/points".into(),
            imu_topic: None,
        }),
        poses: Some(bag_poses.clone()),
        scans: ScanRange::ALL,
        build_poses: false,
        refine_only: false,
    };
    let map = dir.join(format!("kfmap-bench-bake-{}.kfmap", std::process::id()));
    let config = BakeConfig::default();
    let bake_s = |input: &BakeInput| -> anyhow::Result<f64> {
        let _ = std::fs::remove_file(&map);
        let started = Instant::now();
        bake(input, &config, &BakeOutput::map(&map), |_| {})?;
        Ok(started.elapsed().as_secs_f64())
    };
    let reps = if table.quick { 1 } else { 3 };
    let (mut folder_s, mut bag_s) = (f64::INFINITY, f64::INFINITY);
    // Interleaved, best of each: the VM's speed drifts between minutes.
    for _ in 0..reps {
        folder_s = folder_s.min(bake_s(&folder)?);
        bag_s = bag_s.min(bake_s(&from_bag)?);
    }
    let _ = std::fs::remove_file(&map);
    let _ = std::fs::remove_file(&bag);
    let _ = std::fs::remove_file(&bag_poses);
    let label = "balm_os0 scans 0-59 at poses.txt, default bake.toml";
    let threads = rayon::current_num_threads();
    table.push("bake from scan files", label, threads, folder_s, "s");
    table.push(
        "bake from an MCAP of the same clouds",
        label,
        threads,
        bag_s,
        "s",
    );
    table.push(
        "bake from the bag, time as a share of from files",
        label,
        threads,
        100.0 * bag_s / folder_s,
        "%",
    );
    Ok(())
}

/// An MCAP of `clouds` synthetic clouds in ouster-ros's PointCloud2 layout, 10 Hz.
fn write_ouster_mcap(path: &Path, clouds: usize) -> anyhow::Result<()> {
    let fields = [
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("intensity", 16, 7),
        ("t", 20, 6),
        ("reflectivity", 24, 4),
        ("ring", 26, 4),
        ("ambient", 28, 4),
        ("range", 32, 6),
    ];
    let mut data = vec![0u8; CLOUD_POINTS * POINT_STEP];
    for (i, point) in data.chunks_exact_mut(POINT_STEP).enumerate() {
        let (ring, column) = (i / 1024, i % 1024);
        let azimuth = column as f32 / 1024.0 * std::f32::consts::TAU;
        let range = 5.0 + (i % 97) as f32 * 0.3;
        let elevation = (ring as f32 - 64.0) * 0.006;
        let xyz = [
            range * azimuth.cos() * elevation.cos(),
            range * azimuth.sin() * elevation.cos(),
            range * elevation.sin(),
        ];
        for (k, v) in xyz.iter().enumerate() {
            point[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
        }
        point[16..20].copy_from_slice(&(ring as f32).to_le_bytes());
        point[20..24].copy_from_slice(&((column as u32) * 97_656).to_le_bytes());
        point[26..28].copy_from_slice(&(ring as u16).to_le_bytes());
    }
    let messages = (0..clouds).map(|k| {
        let stamp = 1_700_000_000_000_000_000 + k as u64 * 100_000_000;
        (
            stamp,
            cdr_point_cloud2(stamp, 128, 1024, &fields, POINT_STEP, &data),
        )
    });
    write_mcap(path, messages)
}

/// An MCAP of `scans` (PCD files) at the stamps of `poses` (TUM), as the bake reads them.
fn write_clouds_mcap(path: &Path, scans: &[PathBuf], poses: &Path) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(poses).with_context(|| poses.display().to_string())?;
    let stamps: Vec<u64> = text
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| stamp_ns(l.split_whitespace().next().unwrap_or("0")))
        .collect();
    let mut messages = Vec::with_capacity(scans.len());
    for (scan, &stamp) in scans.iter().zip(&stamps) {
        let cloud: PointCloud = read_cloud(scan, &ReadOptions::default())?.cloud;
        let data: Vec<u8> = cloud
            .points
            .iter()
            .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
            .collect();
        let fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)];
        let width = cloud.len();
        messages.push((stamp, cdr_point_cloud2(stamp, 1, width, &fields, 12, &data)));
    }
    write_mcap(path, messages.into_iter())
}

/// A decimal seconds string as nanoseconds, split at the point (no float rounding).
fn stamp_ns(text: &str) -> u64 {
    let (whole, frac) = text.split_once('.').unwrap_or((text, ""));
    let frac: String = frac.chars().chain(std::iter::repeat('0')).take(9).collect();
    whole.parse::<u64>().unwrap_or(0) * 1_000_000_000 + frac.parse::<u64>().unwrap_or(0)
}

/// Writes `(log time ns, CDR bytes)` messages on `/points` as an MCAP (the mcap crate's
/// writer: zstd-compressed chunks by default, as `ros2 bag record` writes them, but
/// uncompressed here: the row measures kfmap's reading, not zstd).
fn write_mcap(path: &Path, messages: impl Iterator<Item = (u64, Vec<u8>)>) -> anyhow::Result<()> {
    let file = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| path.display().to_string())?,
    );
    let mut writer = mcap::WriteOptions::new()
        .compression(None)
        .profile("ros2")
        .create(file)?;
    let schema = writer.add_schema("sensor_msgs/msg/PointCloud2", "ros2msg", b"")?;
    let channel = writer.add_channel(schema, "/points", "cdr", &BTreeMap::new())?;
    for (sequence, (stamp, data)) in messages.enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: sequence as u32,
            log_time: stamp,
            publish_time: stamp,
        };
        writer.write_to_known_channel(&header, &data)?;
    }
    writer.finish()?;
    Ok(())
}

/// A `sensor_msgs/msg/PointCloud2` in little-endian CDR (encapsulation header, fields
/// aligned to their size from the end of that header).
fn cdr_point_cloud2(
    stamp_ns: u64,
    height: usize,
    width: usize,
    fields: &[(&str, u32, u8)],
    point_step: usize,
    data: &[u8],
) -> Vec<u8> {
    let mut out = vec![0x00, 0x01, 0x00, 0x00];
    let align = |out: &mut Vec<u8>, n: usize| {
        while !(out.len() - 4).is_multiple_of(n) {
            out.push(0);
        }
    };
    let u32_le = |out: &mut Vec<u8>, v: u32| {
        align(out, 4);
        out.extend_from_slice(&v.to_le_bytes());
    };
    let string = |out: &mut Vec<u8>, s: &str| {
        u32_le(out, s.len() as u32 + 1);
        out.extend_from_slice(s.as_bytes());
        out.push(0);
    };
    u32_le(&mut out, (stamp_ns / 1_000_000_000) as u32);
    u32_le(&mut out, (stamp_ns % 1_000_000_000) as u32);
    string(&mut out, "lidar");
    u32_le(&mut out, height as u32);
    u32_le(&mut out, width as u32);
    u32_le(&mut out, fields.len() as u32);
    for &(name, offset, datatype) in fields {
        string(&mut out, name);
        u32_le(&mut out, offset);
        out.push(datatype);
        u32_le(&mut out, 1);
    }
    out.push(0); // is_bigendian
    u32_le(&mut out, point_step as u32);
    u32_le(&mut out, (point_step * width) as u32);
    u32_le(&mut out, data.len() as u32);
    out.extend_from_slice(data);
    out.push(1); // is_dense
    out
}
