//! `kfmap gravity`: the gravity direction of a dataset's trajectory from its IMU log.

use std::path::PathBuf;

use anyhow::Context;
use kfmap_bake::config::BakeConfig;
use kfmap_bake::gravity::{GravityInput, PerKeyframe, estimate_dataset_gravity};
use kfmap_bake::source::ImuSource;
use kfmap_client::GravityAnswer;
use kfmap_geometry::gravity::{AccelBias, GravityCorrection};
use kfmap_geometry::options::ConfigFile;
use serde_json::{Value, json};

/// Estimate gravity in a trajectory's frame from its IMU log: every --keyframe-interval
/// seconds a pose becomes a keyframe, the accelerometer samples since the previous one
/// are averaged, and a robust (Huber IRLS) mean of those averages, rotated into the
/// trajectory frame, gives gravity. Prints the gravity vector, the correction (roll and
/// pitch, yaw 0) that makes the frame +Z up, and the pool's health: members, inliers,
/// and the spread of the per-keyframe directions in m/s^2 and degrees.
///
/// Motion compensation (on unless --no-motion-compensation): on a moving platform the
/// accelerometer also feels its own acceleration. Each sample is rotated by the
/// trajectory's attitude at its time and the acceleration implied by the positions
/// (velocity change over the window) is subtracted before pooling; a keyframe whose
/// window the poses do not cover (the first pose's: nothing before it) is left out, as
/// a served session leaves such windows out. The uncompensated estimate is printed
/// beside it.
///
/// Accelerometer bias ([gravity] estimate-accel-bias, on by default): a constant
/// body-frame bias is estimated with gravity (R_i (a_i - b) = g over the keyframes) and
/// printed with its standard deviation per axis and whether the motion determined it
/// ("observable": the platform turned enough; otherwise its prior holds it near 0).
/// --json adds accel_bias_mps2, bias_observable and compensated.
///
/// Inputs: --dataset DIR finds DIR/imu.csv (or imu.txt) and the first of
/// DIR/poses_gt.txt, poses.txt, traj.txt; --imu and --poses override either. Poses are
/// TUM (t x y z qx qy qz qw, T_map_body, on the IMU's clock); the IMU log is
/// `t,ax,ay,az,gx,gy,gz` (m/s^2, rad/s, body frame) or the same columns space-separated.
/// Aligner options come from the [gravity] section of a bake.toml (--config).
/// From a bag: --bag PATH --imu-topic TOPIC reads sensor_msgs/Imu messages (samples at
/// their header stamps) instead of the IMU log; --poses is then required.
///
/// Examples:
///   kfmap simulate --preset courtyard --seconds 30 --tilt-deg 2,-3 --out /tmp/tilted
///   kfmap gravity --dataset /tmp/tilted
///   kfmap gravity --dataset ../shared/data/imu_real --per-keyframe --json
///   kfmap gravity --bag run.mcap --imu-topic /imu --poses run.tum
#[derive(clap::Args)]
#[command(verbatim_doc_comment)]
pub struct Args {
    /// Dataset folder holding the IMU log and the poses.
    #[arg(long, required_unless_present_any = ["imu", "bag"], conflicts_with = "bag")]
    dataset: Option<PathBuf>,
    /// IMU log; default: found in the dataset folder.
    #[arg(long, conflicts_with = "bag")]
    imu: Option<PathBuf>,
    /// A bag (MCAP, rosbag2 sqlite3, ROS 1) whose --imu-topic gives the IMU samples.
    #[arg(long, value_name = "PATH", requires_all = ["imu_topic", "poses"])]
    bag: Option<PathBuf>,
    /// With --bag: the sensor_msgs/Imu topic.
    #[arg(long, value_name = "TOPIC", requires = "bag")]
    imu_topic: Option<String>,
    /// TUM pose file; default: found in the dataset folder.
    #[arg(long)]
    poses: Option<PathBuf>,
    /// Seconds between keyframes.
    #[arg(long, default_value_t = 1.0, value_parser = positive_seconds)]
    keyframe_interval: f64,
    /// bake.toml whose [gravity] section sets the aligner (defaults otherwise).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Pool raw accelerometer means (MOLA's behaviour).
    #[arg(long)]
    no_motion_compensation: bool,
    /// Also print a correction per keyframe from its neighbours.
    #[arg(long)]
    per_keyframe: bool,
    /// Keyframes on each side in a per-keyframe window.
    #[arg(long, default_value_t = 5)]
    half_width: usize,
    /// Members a per-keyframe window needs.
    #[arg(long, default_value_t = 3)]
    min_pool_per_kf: usize,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn positive_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a positive number of seconds")),
    }
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let mut params = BakeConfig::load(args.config.as_deref())?.gravity;
    if args.no_motion_compensation {
        params.motion_compensation = false;
    }
    let input = match (&args.bag, &args.imu_topic, &args.poses) {
        (Some(bag), Some(topic), Some(poses)) => GravityInput {
            imu: ImuSource::Topic {
                bag: bag.clone(),
                topic: topic.clone(),
            },
            poses: poses.clone(),
            keyframe_interval: args.keyframe_interval,
        },
        _ => GravityInput::in_dataset(
            args.dataset.as_deref().unwrap_or(std::path::Path::new(".")),
            args.imu.clone(),
            args.poses.clone(),
            args.keyframe_interval,
        )?,
    };
    let per_keyframe = args.per_keyframe.then_some(PerKeyframe {
        half_width: args.half_width,
        min_pool: args.min_pool_per_kf,
    });
    let report = estimate_dataset_gravity(&input, &params, per_keyframe)
        .with_context(|| format!("gravity from {}", input.imu.label().display()))?;
    let Some(correction) = report.correction else {
        anyhow::bail!(
            "only {} keyframes have IMU samples; the estimate needs min-keyframes = {} \
             (record longer, or lower --keyframe-interval)",
            report.fill.with_samples,
            params.min_keyframes
        );
    };
    if args.json {
        let per_kf: Vec<Value> = report
            .per_keyframe
            .iter()
            .map(|(id, c)| {
                json!({ "keyframe": id, "t": report.keyframe_times[id], "roll_deg": c.roll_deg(),
                        "pitch_deg": c.pitch_deg(), "members": c.estimate.health.members })
            })
            .collect();
        let out = json!({
            "imu": input.imu.label(), "poses": input.poses, "pose_count": report.poses,
            "imu_samples": report.imu_samples, "pool": report.fill,
            "motion_compensation": params.motion_compensation,
            "compensated": report.fill.with_samples > 0 && report.fill.compensated == report.fill.with_samples,
            "accel_bias_mps2": correction.estimate.accel_bias.mps2.as_slice(),
            "bias_observable": correction.estimate.accel_bias.observable,
            "gravity": correction_json(&correction),
            "roll_deg": correction.roll_deg(), "pitch_deg": correction.pitch_deg(),
            "members": correction.estimate.health.members,
            "uncompensated": report.uncompensated.as_ref().map(correction_json),
            "per_keyframe": per_kf,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "{} poses, {} IMU samples; {} keyframes every {} s, {} pooled ({} motion-compensated, \
         {} left out: the poses do not cover their window)",
        report.poses,
        report.imu_samples,
        report.fill.keyframes,
        args.keyframe_interval,
        report.fill.with_samples,
        report.fill.compensated,
        report.fill.skipped
    );
    let label = if params.motion_compensation {
        "motion-compensated"
    } else {
        "raw accelerometer means"
    };
    print_correction(label, &correction);
    if let Some(raw) = &report.uncompensated {
        print_correction("without motion compensation", raw);
        println!(
            "  compensated vs raw direction: {:.3} deg apart",
            correction.estimate.g.angle(&raw.estimate.g).to_degrees()
        );
    }
    if !report.per_keyframe.is_empty() {
        println!("per keyframe (half width {}):", args.half_width);
        println!(
            "  {:>8} {:>12} {:>9} {:>9} {:>7}",
            "keyframe", "t (s)", "roll", "pitch", "members"
        );
        for (id, c) in &report.per_keyframe {
            println!(
                "  {id:>8} {:>12.3} {:>8.3}° {:>8.3}° {:>7}",
                report.keyframe_times[id],
                c.roll_deg(),
                c.pitch_deg(),
                c.estimate.health.members
            );
        }
    }
    Ok(())
}

fn correction_json(c: &GravityCorrection) -> Value {
    let g = c.estimate.g;
    json!({
        "vector": [g.x, g.y, g.z], "norm": g.norm(),
        "roll_deg": c.roll_deg(), "pitch_deg": c.pitch_deg(), "yaw_deg": c.yaw().to_degrees(),
        "health": c.estimate.health,
        "accel_bias": bias_json(&c.estimate.accel_bias),
    })
}

/// An accelerometer bias estimate as JSON: `accel_bias_mps2` `[x, y, z]` (body frame),
/// its standard deviations, and whether the motion made it observable.
pub fn bias_json(b: &AccelBias) -> Value {
    json!({
        "accel_bias_mps2": b.mps2.as_slice(),
        "accel_bias_sigma_mps2": b.sigma_mps2.map(|s| s.as_slice().to_vec()),
        "bias_observable": b.observable,
    })
}

/// One line on an accelerometer bias estimate.
pub fn bias_line(b: &AccelBias) -> String {
    let [x, y, z] = [b.mps2.x, b.mps2.y, b.mps2.z];
    match b.sigma_mps2 {
        Some(s) => format!(
            "accelerometer bias [{x:.4}, {y:.4}, {z:.4}] +- [{:.4}, {:.4}, {:.4}] m/s^2 (body), {}",
            s.x,
            s.y,
            s.z,
            if b.observable {
                "observable"
            } else {
                "not yet observable: the platform has not turned enough; held near 0 by its prior"
            }
        ),
        None => "accelerometer bias not estimated".to_string(),
    }
}

fn print_correction(label: &str, c: &GravityCorrection) {
    let g = c.estimate.g;
    let h = &c.estimate.health;
    println!("{label}:");
    println!(
        "  gravity (trajectory frame): [{:.4}, {:.4}, {:.4}] m/s^2, |g| = {:.4}",
        g.x,
        g.y,
        g.z,
        g.norm()
    );
    println!(
        "  correction to +Z up: roll {:.3}°, pitch {:.3}° (yaw 0)",
        c.roll_deg(),
        c.pitch_deg()
    );
    println!(
        "  pool: {} members, {} within the Huber threshold, effective weight {:.1}, spread {:.3} m/s^2 / {:.3}°",
        h.members, h.inliers, h.effective_weight, h.spread_mps2, h.spread_deg
    );
    println!("  {}", bias_line(&c.estimate.accel_bias));
}

/// A served gravity pool (an `ImuWindow` answer, or a session in a status report) as
/// JSON: the correction, the pool's health and the accelerometer bias.
pub fn served_json(g: &GravityAnswer) -> Value {
    json!({
        "vector": g.gravity,
        "roll_deg": g.roll_pitch[0].to_degrees(),
        "pitch_deg": g.roll_pitch[1].to_degrees(),
        "members": g.members,
        "inliers": g.inliers,
        "spread_deg": g.spread_deg,
        "compensated": g.compensated(),
        "compensated_members": g.compensated,
        "pending": g.pending,
        "skipped": g.skipped,
        "accel_bias_mps2": g.accel_bias_mps2,
        "accel_bias_sigma_mps2": g.accel_bias_sigma_mps2,
        "bias_observable": g.bias_observable,
    })
}

/// A served gravity pool on one line.
pub fn served_line(g: &GravityAnswer) -> String {
    let windows = format!(
        "{} windows ({} motion-compensated, {} pending, {} left out)",
        g.members, g.compensated, g.pending, g.skipped
    );
    if g.gravity.is_none() {
        return format!("{windows}, too few for gravity");
    }
    let [x, y, z] = g.accel_bias_mps2;
    format!(
        "roll {:.3} deg, pitch {:.3} deg from {windows}, {} inliers, spread {:.3} deg; accelerometer bias [{x:.4}, {y:.4}, {z:.4}] m/s^2 ({})",
        g.roll_pitch[0].to_degrees(),
        g.roll_pitch[1].to_degrees(),
        g.inliers,
        g.spread_deg,
        if g.bias_observable {
            "observable"
        } else {
            "not yet observable"
        }
    )
}
