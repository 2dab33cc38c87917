//! `kfmap inspect-bag`: what is in a bag, and how kfmap would read its point clouds.

use std::path::PathBuf;

use anyhow::Context;
use kfmap_bag::msg::{PointCloud2, TimeUnit, datatype_name, decode_point_cloud2};
use kfmap_bag::{Bag, Topic};
use serde_json::{Value, json};

/// Report a bag: its storage format, duration, and every topic with its message type,
/// count and rate; for each sensor_msgs/PointCloud2 topic the first cloud's layout
/// (fields with offset, datatype and count; point_step, height x width, is_dense,
/// frame_id, points per cloud) and which field gives per-point time (and how kfmap
/// reads it), for choosing --points-topic and --imu-topic.
///
/// Bags: MCAP (.mcap, the ROS 2 default since Iron), rosbag2 sqlite3 (.db3, or the
/// rosbag2 folder with metadata.yaml) and ROS 1 (.bag, format 2.0; chunks plain, bz2 or
/// lz4). The bag is not read whole: topics and counts come from its index (summary,
/// index records or SQL), and only the first cloud of each PointCloud2 topic is decoded.
///
/// Then, for example:
///   kfmap inspect-bag run.mcap
///   kfmap bake --bag run.mcap --points-topic /ouster/points --imu-topic /ouster/imu \
///       --build-poses --out run.kfmap --trajectory-out run.tum
///   kfmap localize --map-name run --bag run2.mcap --points-topic /ouster/points
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// The bag: a .mcap, .db3 or .bag file, or a rosbag2 folder.
    path: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let bag = Bag::open(&args.path)?;
    let mut clouds = Vec::new();
    for topic in bag.topics().iter().filter(|t| t.is_point_cloud()) {
        clouds.push((topic.name.clone(), first_cloud(&bag, topic)?));
    }
    let first = bag.topics().iter().filter_map(|t| t.first_ns).min();
    let last = bag.topics().iter().filter_map(|t| t.last_ns).max();
    let duration = first.zip(last).map(|(a, b)| (b - a) as f64 * 1e-9);
    if args.json {
        let topics: Vec<Value> = bag
            .topics()
            .iter()
            .map(|t| {
                let layout = clouds.iter().find(|(name, _)| name == &t.name);
                json!({
                    "name": t.name, "type": t.msg_type, "count": t.count, "rate_hz": rate(t),
                    "encoding": format!("{:?}", t.encoding).to_lowercase(),
                    "first_ns": t.first_ns, "last_ns": t.last_ns,
                    "point_cloud": layout.map(|(_, l)| l.clone()),
                })
            })
            .collect();
        let out = json!({
            "path": bag.path(), "storage": bag.storage().to_string(),
            "duration_s": duration, "start_ns": first, "end_ns": last, "topics": topics,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!("{}", bag.path().display());
    println!("  storage   {}", bag.storage());
    match duration {
        Some(d) => println!("  duration  {d:.3} s"),
        None => println!("  duration  - (no messages)"),
    }
    println!("  topics    {}", bag.topics().len());
    let width = bag.topics().iter().map(|t| t.name.len()).max().unwrap_or(5);
    for t in bag.topics() {
        let hz = rate(t).map_or("-".to_string(), |r| format!("{r:.2} Hz"));
        println!(
            "    {:width$}  {:32}  {:>8} msgs  {hz}",
            t.name, t.msg_type, t.count
        );
    }
    for (name, layout) in &clouds {
        println!("  {name}: first cloud");
        print_layout(layout);
    }
    Ok(())
}

/// Messages per second over the topic's span.
fn rate(t: &Topic) -> Option<f64> {
    let (a, b) = t.first_ns.zip(t.last_ns)?;
    (t.count > 1 && b > a).then(|| (t.count - 1) as f64 / ((b - a) as f64 * 1e-9))
}

/// The layout of `topic`'s first cloud, as JSON (`null` fields when it has none).
fn first_cloud(bag: &Bag, topic: &Topic) -> anyhow::Result<Value> {
    let Some(at) = bag.index(topic)?.into_iter().next() else {
        return Ok(Value::Null);
    };
    let message = bag.read(&at)?;
    let cloud = decode_point_cloud2(&message.data, topic.encoding)
        .with_context(|| format!("{}: first message of {}", bag.path().display(), topic.name))?;
    Ok(layout_json(&cloud))
}

/// A cloud's layout: fields, sizes, frame, and the time and ring fields kfmap uses.
fn layout_json(cloud: &PointCloud2) -> Value {
    let fields: Vec<Value> = cloud
        .fields
        .iter()
        .map(|f| {
            json!({ "name": f.name, "offset": f.offset, "datatype": datatype_name(f.datatype),
                    "count": f.count })
        })
        .collect();
    let time = cloud.time_field().map(|t| {
        let unit = match t.unit {
            TimeUnit::RelativeNanos => "ns after the header stamp",
            TimeUnit::RelativeSeconds => "s after the header stamp",
            TimeUnit::AbsoluteSeconds => "s since the epoch",
            TimeUnit::AbsoluteNanos => "ns since the epoch",
        };
        json!({ "field": t.name, "unit": unit })
    });
    json!({
        "frame_id": cloud.frame_id, "stamp_s": cloud.stamp.seconds(),
        "height": cloud.height, "width": cloud.width, "points": cloud.len(),
        "point_step": cloud.point_step, "row_step": cloud.row_step,
        "is_dense": cloud.is_dense, "is_bigendian": cloud.is_bigendian,
        "fields": fields, "time": time, "ring": cloud.ring_field().map(|f| f.name.clone()),
    })
}

/// The text form of [`layout_json`].
fn print_layout(layout: &Value) {
    if layout.is_null() {
        println!("    (no messages)");
        return;
    }
    let v = |k: &str| layout[k].to_string();
    println!(
        "    frame_id {}  {} x {} = {} points  point_step {}  row_step {}  is_dense {}{}",
        layout["frame_id"].as_str().unwrap_or(""),
        v("height"),
        v("width"),
        v("points"),
        v("point_step"),
        v("row_step"),
        v("is_dense"),
        if layout["is_bigendian"] == true {
            "  big-endian"
        } else {
            ""
        }
    );
    println!(
        "    {:16} {:>6}  {:8} {:>5}",
        "field", "offset", "datatype", "count"
    );
    for f in layout["fields"].as_array().into_iter().flatten() {
        println!(
            "    {:16} {:>6}  {:8} {:>5}",
            f["name"].as_str().unwrap_or(""),
            f["offset"],
            f["datatype"].as_str().unwrap_or(""),
            f["count"]
        );
    }
    match &layout["time"] {
        Value::Null => println!(
            "    per-point time: none (scans are taken as deskewed already; --deskew azimuth times a spinning sensor's sweep)"
        ),
        t => println!(
            "    per-point time: field '{}', {}",
            t["field"].as_str().unwrap_or(""),
            t["unit"].as_str().unwrap_or("")
        ),
    }
    if let Some(ring) = layout["ring"].as_str() {
        println!("    ring: field '{ring}'");
    }
}
