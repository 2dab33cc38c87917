//! The node: DDS readers forward messages into channels (on a smol executor thread, as
//! ros2-client runs its spinner), and one loop localizes each cloud through the local
//! `kfmap serve` with the same tracker `kfmap localize` uses, then publishes.

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use futures::StreamExt;
use kfmap_bag::Encoding;
use kfmap_bag::msg::{ImuMessage, PointCloud2, decode_header, decode_imu, decode_point_cloud2};
use kfmap_client::{Client, ClientOptions, LocalizeOptions, TrackedScan, Tracker, TrackerOptions};
use kfmap_geometry::cloud::PointCloud;
use kfmap_geometry::geometry::Pose;
use kfmap_geometry::imu::ImuSample;
use kfmap_geometry::motion::GyroParams;
use kfmap_map::archive::{OpenOptions, open_map};
use kfmap_protocol::Cov2CovMode;
use ros2_client::dds::rustdds::{Topic, no_key};
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher,
    QosProfile, Subscription,
};

use crate::cloud::{BadCloud, scan_of, xyz_sample};
use crate::config::{ModeName, Ros2Config};
use crate::frames::{Frames, parse_mounting, sensor_mounting};
use crate::keep_last::KeepLast;
use crate::msgs::{
    DiagnosticArray, Header, Odometry, PoseWithCovarianceStamped, Stamp, TfMessage, Vector3Stamped,
};
use crate::outputs::{Condition, FrameNames, base_velocity, diagnostics, scan_outputs};
use crate::raw::{self, CdrSample, RawCdr};

/// How long the loop waits for a cloud before it looks at the stop flag again.
const IDLE: Duration = Duration::from_millis(100);
/// Diagnostics are published at least this often while no cloud arrives.
const DIAGNOSTICS_PERIOD: Duration = Duration::from_secs(1);

/// What the node did, for its closing line.
#[derive(Debug, Default, Clone)]
pub struct Summary {
    /// Clouds received.
    pub received: u64,
    /// Clouds localized (a pose published unless lost or held back, `unmounted`).
    pub localized: u64,
    /// Clouds localized whose pose was held back: their frame's mounting on the base was
    /// not known yet (no `/tf_static` chain, no `[frames] sensor-mounting`).
    pub unmounted: u64,
    /// Clouds skipped for newer ones while the loop was behind (`[qos] points-depth`
    /// kept: the newest).
    pub skipped: u64,
    /// IMU samples dropped for newer ones (more than `[qos] imu-depth` between clouds).
    pub imu_dropped: u64,
    /// Clouds refused (bad layout, no valid point).
    pub bad: u64,
    /// Clouds that found no server.
    pub unanswered: u64,
}

/// A message and when its reader took it.
type Arrived<M> = (M, Instant);

/// A reader's queue into the loop.
type Queue<M> = Arc<KeepLast<Arrived<M>>>;

/// Messages from the readers.
struct Inbox {
    /// `PointCloud2` samples, decoded by the loop (their points stay in the sample).
    clouds: Queue<CdrSample>,
    imu: Queue<ImuMessage>,
    initial: Queue<PoseWithCovarianceStamped>,
    tf: Queue<TfMessage>,
    tf_static: Queue<TfMessage>,
}

/// The node's publishers.
struct Outbox {
    pose: Publisher<PoseWithCovarianceStamped>,
    odometry: Publisher<Odometry>,
    tf: Publisher<TfMessage>,
    diagnostics: Publisher<DiagnosticArray>,
    map_cloud: Option<no_key::DataWriter<CdrSample, RawCdr>>,
    gravity: Option<Publisher<Vector3Stamped>>,
}

/// A topic name split as ros2-client wants it.
fn topic_name(full: &str) -> anyhow::Result<Name> {
    Name::parse(full).map_err(|e| anyhow::anyhow!("topic {full}: {e:?}"))
}

fn reliable(depth: usize) -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .history(History::KeepLast { depth })
}

fn latched() -> QosProfile {
    reliable(1).durability(Durability::TransientLocal)
}

fn sensor_data(depth: usize) -> QosProfile {
    QosProfile::subscription_default().history(History::KeepLast { depth })
}

/// A ROS 2 message type: its package and name (`sensor_msgs`, `PointCloud2`).
type RosType = (&'static str, &'static str);

fn topic(
    node: &Node,
    name: &str,
    (package, type_name): RosType,
    qos: &QosProfile,
) -> anyhow::Result<Topic> {
    node.create_topic(
        &topic_name(name)?,
        MessageTypeName::new(package, type_name),
        qos,
    )
    .with_context(|| format!("create topic {name}"))
}

fn subscribe<M: 'static>(
    node: &mut Node,
    name: &str,
    ros_type: RosType,
    qos: QosProfile,
) -> anyhow::Result<Subscription<M>> {
    let t = topic(node, name, ros_type, &qos)?;
    node.create_subscription::<M>(&t, Some(qos))
        .with_context(|| format!("subscribe to {name}"))
}

fn publish_on<M: serde::Serialize>(
    node: &mut Node,
    name: &str,
    ros_type: RosType,
    qos: QosProfile,
) -> anyhow::Result<Publisher<M>> {
    let t = topic(node, name, ros_type, &qos)?;
    node.create_publisher::<M>(&t, Some(qos))
        .with_context(|| format!("publish on {name}"))
}

/// Forwards a subscription's messages into `into`, a keep-newest queue (the readers
/// never wait on the loop; a full queue gives up its oldest, counted).
async fn forward<M: 'static + serde::de::DeserializeOwned>(
    subscription: Subscription<M>,
    into: Queue<M>,
    what: &'static str,
) {
    let stream = subscription.async_stream();
    futures::pin_mut!(stream);
    while let Some(item) = stream.next().await {
        match item {
            Ok((message, _)) => into.push((message, Instant::now())),
            // A message that does not deserialize as its type: named, never fatal.
            Err(e) => tracing::warn!("a {what} message could not be read: {e:?}"),
        }
    }
}

/// The tracker options `kfmap localize` uses, from the config.
pub(crate) fn tracker_options(config: &Ros2Config) -> TrackerOptions {
    let mode = match config.server.mode {
        ModeName::MapDefault => Cov2CovMode::MapDefault,
        ModeName::Approximate => Cov2CovMode::Approximate,
        ModeName::Exact => Cov2CovMode::Exact,
    };
    TrackerOptions {
        localize: LocalizeOptions {
            mode,
            ..LocalizeOptions::default()
        },
        server_side: config.server.server_side,
        deskew: config.scans.deskew,
        trust: config.tracker,
        hypotheses: config.hypotheses,
        ..TrackerOptions::default()
    }
}

/// The served map's points in the map frame, thinned to `voxel` metres.
fn map_points(path: &Path, voxel: f64) -> anyhow::Result<Vec<[f32; 3]>> {
    let opened = open_map(
        path,
        OpenOptions {
            trust: true,
            ..OpenOptions::default()
        },
    )
    .with_context(|| format!("open the served map {}", path.display()))?;
    let mut points = Vec::new();
    for keyframe in opened.map.keyframes() {
        let world = keyframe.map_points().context("read a keyframe")?;
        points.extend(world.iter().map(|p| p.map(|v| v as f32)));
    }
    let cloud = PointCloud::from_points(points);
    Ok(cloud
        .voxel_downsample(voxel)
        .context("thin the map")?
        .points)
}

/// The state of one run.
struct Localizer<'a> {
    config: &'a Ros2Config,
    frames: Frames,
    names: FrameNames,
    /// `[frames] sensor-mounting`, parsed once (`None` when empty).
    configured_mounting: Option<Pose>,
    client: Option<Client>,
    tracker: Tracker,
    /// `/initialpose` received, applied to the next cloud (its frame gives the mounting).
    initial: Option<Pose>,
    /// IMU samples since the last cloud.
    imu: Vec<ImuSample>,
    /// Samples this buffer gave up, oldest first, past `[qos] imu-depth`.
    imu_overflow: u64,
    /// The IMU messages' frame (the last one read).
    imu_frame: Option<String>,
    /// The last published base pose and its stamp.
    last_base: Option<(f64, Pose)>,
    scans: u64,
    gravity_published: bool,
    summary: Summary,
    last_diagnostics: Instant,
    /// The last tracked cloud's time from its arrival to its pose published, for the
    /// diagnostics that follow it.
    latency_ms: Option<f64>,
}

impl Localizer<'_> {
    fn client(&mut self) -> Result<&mut Client, String> {
        connected(&mut self.client, self.config)
    }

    /// `T_base_sensor` for a cloud in `frame` ([`sensor_mounting`]); `None` while a
    /// latched `/tf_static` may still be on its way.
    fn mounting(&self, frame: &str) -> Option<Pose> {
        sensor_mounting(
            &self.frames,
            &self.names.base,
            frame,
            self.configured_mounting,
        )
    }

    fn publish_diagnostics(&mut self, out: &Outbox, stamp: Stamp, condition: &Condition<'_>) {
        let counters = [
            ("clouds", self.summary.received.to_string()),
            ("localized", self.summary.localized.to_string()),
            ("skipped", self.summary.skipped.to_string()),
            ("imu_dropped", self.summary.imu_dropped.to_string()),
            ("bad", self.summary.bad.to_string()),
            ("unanswered", self.summary.unanswered.to_string()),
            ("unmounted", self.summary.unmounted.to_string()),
        ];
        let latency = self
            .latency_ms
            .take()
            .map(|ms| ("latency_ms", format!("{ms:.3}")));
        let counters: Vec<_> = counters.into_iter().chain(latency).collect();
        let message = diagnostics(stamp, condition, &self.config.server.map_name, &counters);
        if let Err(e) = out.diagnostics.publish(message) {
            tracing::warn!("diagnostics not published: {e:?}");
        }
        self.last_diagnostics = Instant::now();
    }

    /// Decodes one `PointCloud2` sample, which its reader took at `arrived`, and
    /// localizes it ([`Self::on_cloud`]); one that does not decode is counted as bad.
    fn on_sample(&mut self, sample: &CdrSample, arrived: Instant, out: &Outbox) {
        match decode_point_cloud2(&sample.0, Encoding::Cdr) {
            Ok(msg) => self.on_cloud(&msg, arrived, out),
            Err(e) => {
                self.summary.bad += 1;
                let why = format!("cannot read the cloud: {e}");
                // Said at the cloud's stamp when its header reads, as for any bad cloud.
                let stamp = decode_header(&sample.0, Encoding::Cdr)
                    .map_or_else(|_| Stamp::from_seconds(now_seconds()), |(stamp, _)| stamp);
                tracing::warn!("cloud at {:.3}: {why}", stamp.seconds());
                self.publish_diagnostics(out, stamp, &Condition::BadCloud(&why));
            }
        }
    }

    /// Localizes one cloud, which its reader took at `arrived`, and publishes what
    /// follows from it.
    fn on_cloud(&mut self, msg: &PointCloud2<'_>, arrived: Instant, out: &Outbox) {
        let stamp = msg.stamp;
        let t = stamp.seconds();
        let queued = arrived.elapsed();
        let scan = match scan_of(msg, &self.config.scans) {
            Ok(scan) => scan,
            Err(e) => {
                self.summary.bad += 1;
                let why = e.to_string();
                if !matches!(e, BadCloud::NoValidPoint(_)) {
                    tracing::warn!("cloud at {t:.3}: {why}");
                }
                self.publish_diagnostics(out, stamp, &Condition::BadCloud(&why));
                return;
            }
        };
        let mounting = self.mounting(&msg.frame_id);
        // Without the mounting an /initialpose (of the base) waits, and the gyro (whose
        // IMU is mounted relative to the base) is not fed; tracking goes on.
        if let Some(base_sensor) = mounting {
            if let Some(map_base) = self.initial.take() {
                let options = tracker_options(self.config);
                // The gyro's log and bias carry over to the new track.
                let mut tracker = Tracker::new(map_base * base_sensor, options);
                if let Some(gyro) = self.tracker.gyro().cloned() {
                    tracker = tracker.with_gyro(gyro);
                }
                self.tracker = tracker;
                tracing::info!("tracking restarted from /initialpose");
            }
            self.feed_gyro(&base_sensor);
        }
        let prepared = arrived.elapsed();
        let tracked: Result<TrackedScan, String> = match connected(&mut self.client, self.config) {
            Ok(client) => self
                .tracker
                .track_cloud(client, &scan, t)
                .map_err(|e| e.to_string()),
            Err(e) => Err(e),
        };
        let tracked = match tracked {
            Ok(tracked) => tracked,
            Err(why) => {
                // A server that went away is reached again on a later cloud.
                self.client = None;
                self.summary.unanswered += 1;
                self.tracker.unanswered(t);
                self.publish_diagnostics(out, stamp, &Condition::NoServer(&why));
                return;
            }
        };
        let localized = arrived.elapsed();
        self.summary.localized += 1;
        self.scans += 1;
        let health = tracked.localized.health;
        let map_sensor = tracked.localized.pose;
        let Some(base_sensor) = mounting else {
            self.summary.unmounted += 1;
            let why = format!(
                "no mounting of {:?} on {:?} yet: waiting for /tf_static (or set [frames] sensor-mounting)",
                msg.frame_id, self.names.base
            );
            if self.summary.unmounted == 1 {
                tracing::warn!("cloud at {t:.3}: pose held back, {why}");
            }
            self.publish_diagnostics(out, stamp, &Condition::Unmounted(&why));
            self.push_imu_window(out, stamp, &map_sensor);
            return;
        };
        let sensor_base = base_sensor.inverse();
        let map_base = map_sensor * sensor_base;
        let velocity = self
            .last_base
            .and_then(|(t0, before)| base_velocity(&before, &map_base, t - t0));
        let odom_base = self.frames.odometry_at(t);
        let outputs = scan_outputs(
            &self.names,
            stamp,
            &map_sensor,
            &health,
            &sensor_base,
            odom_base.as_ref(),
            velocity,
        );
        self.last_base = Some((t, map_base));
        let lost = health.status == kfmap_geometry::tracking::TrackingStatus::Lost;
        if !lost {
            if let Err(e) = out.pose.publish(outputs.pose) {
                tracing::warn!("pose not published: {e:?}");
            }
            if let Err(e) = out.odometry.publish(outputs.odometry) {
                tracing::warn!("odometry not published: {e:?}");
            }
            if self.config.frames.publish_tf {
                let tf = TfMessage {
                    transforms: vec![outputs.transform],
                };
                if let Err(e) = out.tf.publish(tf) {
                    tracing::warn!("transform not published: {e:?}");
                }
            }
        }
        // From the reader's take to the pose published (the cloud -> pose).
        let published = arrived.elapsed();
        self.latency_ms = Some(published.as_secs_f64() * 1e3);
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        tracing::debug!(
            points = msg.width * msg.height,
            thinned = scan.len(),
            queued_ms = ms(queued),
            prepare_ms = ms(prepared - queued),
            track_ms = ms(localized - prepared),
            publish_ms = ms(published - localized),
            "cloud at {t:.3} localized"
        );
        self.publish_diagnostics(out, stamp, &Condition::Tracked(&health));
        self.push_imu_window(out, stamp, &map_sensor);
    }

    /// Takes the transforms, initial poses and IMU samples waiting in `inbox`.
    fn read_inputs(&mut self, inbox: &Inbox) {
        for (message, _) in inbox.tf_static.drain() {
            let skipped = self.frames.add_static(&message.transforms);
            if skipped > 0 {
                tracing::warn!(skipped, "malformed /tf_static transforms skipped");
            }
        }
        for (message, _) in inbox.tf.drain() {
            self.frames.add_dynamic(
                &message.transforms,
                &self.config.frames.odom,
                &self.config.frames.base,
            );
        }
        for (message, _) in inbox.initial.drain() {
            match message.pose.pose.pose() {
                Some(pose)
                    if message.header.frame_id.trim_start_matches('/')
                        == self.config.frames.map =>
                {
                    self.initial = Some(pose);
                }
                Some(_) => tracing::warn!(
                    frame = message.header.frame_id,
                    "an initial pose not in the map frame {} is ignored",
                    self.config.frames.map
                ),
                None => tracing::warn!(
                    "an initial pose that is not finite or not a rotation is ignored"
                ),
            }
        }
        for (message, _) in inbox.imu.drain() {
            if self.imu_frame.as_deref() != Some(message.frame_id.as_str()) {
                self.imu_frame = Some(message.frame_id.clone());
            }
            // A sample not finite is dropped: the server would refuse its whole window.
            if let Some(sample) = message.sample() {
                self.imu.push(sample);
            }
        }
        // More than imu-depth since the last cloud (none arrives): the oldest go.
        let excess = self.imu.len().saturating_sub(self.config.qos.imu_depth);
        self.imu.drain(..excess);
        self.imu_overflow += excess as u64;
    }

    /// Copies the readers' counts into the summary.
    fn count(&mut self, inbox: &Inbox) {
        self.summary.received = inbox.clouds.pushed();
        self.summary.skipped = inbox.clouds.evicted();
        self.summary.imu_dropped = inbox.imu.evicted() + self.imu_overflow;
    }

    /// Gives the tracker's gyro the IMU samples read since the last cloud (made on the
    /// first, with the IMU's mounting from /tf_static or the config).
    fn feed_gyro(&mut self, base_sensor: &Pose) {
        if !self.config.imu.gyro || self.imu.is_empty() {
            return;
        }
        // The mounting is read once, when the first samples make the gyro.
        let params = match self.tracker.gyro() {
            Some(gyro) => *gyro.params(),
            None => GyroParams {
                lidar_from_imu_rpy_deg: self.lidar_from_imu_rpy_deg(base_sensor),
                ..GyroParams::default()
            },
        };
        match self
            .tracker
            .push_imu(&self.imu, params, self.config.imu.keep_s)
        {
            Ok(0) => {}
            Ok(refused) => {
                tracing::warn!(refused, "IMU samples out of order or not finite skipped")
            }
            Err(e) => tracing::warn!("no gyro: {e}"),
        }
    }

    /// `R_lidar_imu` as roll, pitch, yaw degrees: from `/tf_static` (base -> IMU frame
    /// and base -> LiDAR), else `[imu] lidar-from-imu-rpy-deg`.
    fn lidar_from_imu_rpy_deg(&self, base_sensor: &Pose) -> [f64; 3] {
        let base_imu = self
            .imu_frame
            .as_deref()
            .and_then(|frame| self.frames.mounting(&self.names.base, frame));
        match base_imu {
            Some(base_imu) => {
                let (r, p, y) = (base_sensor.rotation.inverse() * base_imu.rotation).euler_angles();
                [r, p, y].map(f64::to_degrees)
            }
            None => self.config.imu.lidar_from_imu_rpy_deg,
        }
    }

    /// Sends the IMU samples since the last cloud to the server's gravity pool, and
    /// publishes the gravity direction once it is pooled.
    fn push_imu_window(&mut self, out: &Outbox, stamp: Stamp, map_sensor: &Pose) {
        if self.imu.len() < 2 {
            return;
        }
        let samples = std::mem::take(&mut self.imu);
        let t = stamp.seconds();
        let Some(client) = self.client.as_mut() else {
            return;
        };
        match client.push_imu_window(self.scans, map_sensor, Some(t), &samples) {
            Ok(answer) => {
                if let (Some(publisher), Some(gravity)) = (&out.gravity, answer.gravity) {
                    let message = Vector3Stamped {
                        header: Header {
                            stamp,
                            frame_id: self.names.map.clone(),
                        },
                        vector: nalgebra::Vector3::from(gravity).into(),
                    };
                    if publisher.publish(message).is_ok() && !self.gravity_published {
                        self.gravity_published = true;
                        tracing::info!(
                            "gravity pooled: published on {}",
                            self.config.topics.gravity
                        );
                    }
                }
            }
            Err(e) => tracing::warn!("IMU window at {t:.3}: {e}"),
        }
    }
}

/// The connection to the server in `slot`, made when there is none: tried for every
/// cloud while the server is away (a failed attempt costs about a millisecond), so
/// tracking resumes with the first cloud after it is back.
fn connected<'c>(
    slot: &'c mut Option<Client>,
    config: &Ros2Config,
) -> Result<&'c mut Client, String> {
    if slot.is_none() {
        let options = ClientOptions {
            iceoryx_prefix: (!config.server.iceoryx_prefix.is_empty())
                .then(|| config.server.iceoryx_prefix.clone()),
            timeout: Duration::from_secs_f64(config.server.timeout_s),
            spin: false,
        };
        let client =
            Client::connect(&config.server.map_name, options).map_err(|e| e.to_string())?;
        tracing::info!(map = config.server.map_name, "connected to the server");
        *slot = Some(client);
    }
    Ok(slot.as_mut().expect("connected above"))
}

/// Runs the node until `stop` is set. `ready` is called once every reader and writer
/// exists.
pub fn run(
    config: &Ros2Config,
    domain_id: u16,
    stop: &Arc<AtomicBool>,
    ready: impl FnOnce(),
) -> anyhow::Result<Summary> {
    let context = Context::with_options(ContextOptions::new().domain_id(domain_id))
        .context("start DDS (domain participant)")?;
    let node_name = NodeName::new(&config.node.namespace, &config.node.name)
        .map_err(|e| anyhow::anyhow!("node name: {e:?}"))?;
    let mut node = context
        .new_node(node_name.clone(), NodeOptions::new().enable_rosout(false))
        .context("create the ROS 2 node")?;
    let topics = &config.topics;
    let inbox = Inbox {
        clouds: Arc::new(KeepLast::new(config.qos.points_depth)),
        imu: Arc::new(KeepLast::new(config.qos.imu_depth)),
        initial: Arc::new(KeepLast::new(8)),
        tf: Arc::new(KeepLast::new(256)),
        tf_static: Arc::new(KeepLast::new(64)),
    };
    let executor = Arc::new(smol::Executor::new());
    // The sensors' messages come as bytes, for kfmap_bag's decoders (crate::raw).
    let participant = context.domain_participant();
    let qos = sensor_data(config.qos.points_depth);
    let points_topic = raw::bounded_topic(
        &participant,
        &node_name,
        &topic_name(&topics.points)?,
        &MessageTypeName::new("sensor_msgs", "PointCloud2"),
        &qos,
    )?;
    let points = raw::reader(&participant, &points_topic, &qos)?;
    let clouds = inbox.clouds.clone();
    executor
        .spawn(raw::forward(points, move |sample| {
            clouds.push((sample, Instant::now()));
        }))
        .detach();
    if !topics.imu.is_empty() {
        let qos = sensor_data(config.qos.imu_depth);
        let imu = raw::reader(
            &participant,
            &topic(&node, &topics.imu, ("sensor_msgs", "Imu"), &qos)?,
            &qos,
        )?;
        let queue = inbox.imu.clone();
        executor
            .spawn(raw::forward(imu, move |sample| {
                match decode_imu(&sample.0, Encoding::Cdr) {
                    Ok(message) => queue.push((message, Instant::now())),
                    // A message that does not decode as its type: named, never fatal.
                    Err(e) => tracing::warn!("an Imu message could not be read: {e}"),
                }
            }))
            .detach();
    }
    if !topics.initial_pose.is_empty() {
        let sub = subscribe::<PoseWithCovarianceStamped>(
            &mut node,
            &topics.initial_pose,
            ("geometry_msgs", "PoseWithCovarianceStamped"),
            reliable(8),
        )?;
        executor
            .spawn(forward(
                sub,
                inbox.initial.clone(),
                "PoseWithCovarianceStamped",
            ))
            .detach();
    }
    let sub = subscribe::<TfMessage>(
        &mut node,
        &topics.tf,
        ("tf2_msgs", "TFMessage"),
        reliable(100),
    )?;
    executor
        .spawn(forward(sub, inbox.tf.clone(), "TFMessage"))
        .detach();
    let sub = subscribe::<TfMessage>(
        &mut node,
        &topics.tf_static,
        ("tf2_msgs", "TFMessage"),
        reliable(100).durability(Durability::TransientLocal),
    )?;
    executor
        .spawn(forward(sub, inbox.tf_static.clone(), "TFMessage"))
        .detach();
    let out = Outbox {
        pose: publish_on(
            &mut node,
            &topics.pose,
            ("geometry_msgs", "PoseWithCovarianceStamped"),
            reliable(10),
        )?,
        odometry: publish_on(
            &mut node,
            &topics.odometry,
            ("nav_msgs", "Odometry"),
            reliable(10),
        )?,
        tf: publish_on(
            &mut node,
            &topics.tf,
            ("tf2_msgs", "TFMessage"),
            reliable(100),
        )?,
        diagnostics: publish_on(
            &mut node,
            &topics.diagnostics,
            ("diagnostic_msgs", "DiagnosticArray"),
            reliable(10),
        )?,
        map_cloud: (!topics.map_cloud.is_empty() && config.map_cloud.voxel > 0.0)
            .then(|| {
                let topic = topic(
                    &node,
                    &topics.map_cloud,
                    ("sensor_msgs", "PointCloud2"),
                    &latched(),
                )?;
                raw::writer(&participant, &topic, &latched())
            })
            .transpose()?,
        gravity: (!topics.gravity.is_empty())
            .then(|| {
                publish_on(
                    &mut node,
                    &topics.gravity,
                    ("geometry_msgs", "Vector3Stamped"),
                    latched(),
                )
            })
            .transpose()?,
    };
    let spinner = node.spinner().context("start the node's spinner")?;
    executor.spawn(spinner.spin()).detach();
    let spinning = {
        let executor = executor.clone();
        let stop = stop.clone();
        std::thread::Builder::new()
            .name("kfmap-ros2-dds".into())
            .spawn(move || {
                smol::block_on(executor.run(async {
                    while !stop.load(Ordering::SeqCst) {
                        smol::Timer::after(IDLE).await;
                    }
                }))
            })
            .context("start the DDS thread")?
    };
    ready();
    let summary = run_loop(config, &inbox, &out, stop);
    stop.store(true, Ordering::SeqCst);
    let _ = spinning.join();
    Ok(summary)
}

fn run_loop(config: &Ros2Config, inbox: &Inbox, out: &Outbox, stop: &AtomicBool) -> Summary {
    let mut state = Localizer {
        config,
        frames: Frames::default(),
        names: FrameNames {
            map: config.frames.map.clone(),
            odom: config.frames.odom.clone(),
            base: config.frames.base.clone(),
        },
        configured_mounting: parse_mounting(&config.frames.sensor_mounting),
        client: None,
        tracker: Tracker::relocalizing(tracker_options(config)),
        initial: None,
        imu: Vec::new(),
        imu_overflow: 0,
        imu_frame: None,
        last_base: None,
        scans: 0,
        gravity_published: false,
        summary: Summary::default(),
        last_diagnostics: Instant::now() - DIAGNOSTICS_PERIOD,
        latency_ms: None,
    };
    let (map_tx, map_rx) = std::sync::mpsc::channel();
    let mut map_requested = out.map_cloud.is_none();
    while !stop.load(Ordering::SeqCst) {
        // The map cloud is read once the server names its file, off this loop.
        if !map_requested
            && let Ok(client) = state.client()
            && let Ok(status) = client.status()
        {
            map_requested = true;
            let voxel = config.map_cloud.voxel;
            let tx = map_tx.clone();
            std::thread::spawn(move || {
                let _ = tx.send(map_points(Path::new(&status.map_path), voxel));
            });
        }
        if let (Ok(points), Some(writer)) = (map_rx.try_recv(), &out.map_cloud) {
            let stamp = Stamp::from_seconds(now_seconds());
            let sample = points.and_then(|points| {
                let n = points.len();
                Ok((xyz_sample(stamp, &config.frames.map, &points)?, n))
            });
            match sample {
                Ok((sample, n)) => match writer.write(sample, None) {
                    Ok(()) => tracing::info!(points = n, "map cloud published"),
                    Err(e) => tracing::warn!("map cloud not published: {e:?}"),
                },
                Err(e) => tracing::warn!("no map cloud: {e:#}"),
            }
        }
        state.read_inputs(inbox);
        match inbox.clouds.pop_timeout(IDLE) {
            Some((cloud, arrived)) => {
                // What came in while the loop waited (the IMU up to this cloud).
                state.read_inputs(inbox);
                state.count(inbox);
                state.on_sample(&cloud, arrived, out);
            }
            None => {
                if state.last_diagnostics.elapsed() >= DIAGNOSTICS_PERIOD {
                    state.count(inbox);
                    let stamp = Stamp::from_seconds(now_seconds());
                    let condition = match state.client() {
                        Ok(_) => Condition::Waiting,
                        Err(why) => {
                            let why = why.clone();
                            state.publish_diagnostics(out, stamp, &Condition::NoServer(&why));
                            continue;
                        }
                    };
                    state.publish_diagnostics(out, stamp, &condition);
                }
            }
        }
    }
    state.count(inbox);
    state.summary
}

fn now_seconds() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use kfmap_client::{HypothesisParams, TrustParams};
    use kfmap_geometry::options::ConfigFile;

    use super::tracker_options;
    use crate::config::Ros2Config;

    /// The node's tracker takes `[tracker]` as written, the rest at its defaults.
    #[test]
    fn the_tracker_section_reaches_the_trackers_options() {
        let config = Ros2Config::from_toml(
            "[tracker]\nok-pinned = -1.0\ncheck-every = 0\nok-explained = 0.7",
            Path::new("r.toml"),
        )
        .unwrap();
        let trust = tracker_options(&config).trust;
        assert_eq!(trust.ok_pinned, -1.0);
        assert_eq!(trust.check_every, 0);
        assert_eq!(trust.ok_explained, 0.7);
        assert_eq!(
            trust.lost_after_unfit,
            TrustParams::default().lost_after_unfit
        );
    }

    /// The node's tracker takes `[hypotheses]` as written, the rest at its defaults.
    #[test]
    fn the_hypotheses_section_reaches_the_trackers_options() {
        let config = Ros2Config::from_toml(
            "[hypotheses]
early-spread = 1.0
hold-explained = 0.0
min-scans = 8",
            Path::new("r.toml"),
        )
        .unwrap();
        let hypotheses = tracker_options(&config).hypotheses;
        assert_eq!(hypotheses.early_spread, 1.0);
        assert_eq!(hypotheses.hold_explained, 0.0);
        assert_eq!(hypotheses.min_scans, 8);
        assert_eq!(hypotheses.margin, HypothesisParams::default().margin);
    }
}
