//! ROS 2 over DDS (`[outputs.ros2]`, firmware feature `ros2`; docs/outputs.md): tool poses as
//! `geometry_msgs/msg/PoseStamped`, the single LED as `geometry_msgs/msg/PointStamped`, the loose
//! single LEDs beside tools as one `sensor_msgs/msg/PointCloud2` per set (x y z and `loose_id`), `/tf`
//! (tracker frame → tool frames) and `/tf_static` (robot base → tracker, from the survey's
//! registration), on `ros2-client` over `rustdds` (pure Rust; no ROS installation).
//!
//! The publisher runs on a thread of its own that reads the loop's latest-value slot; a
//! publish that cannot go out at once (reliable QoS with a full send window) is dropped and
//! counted, never waited for, so no reader can slow the loop or the other outputs.

use serde::Deserialize;

use crate::error::{FirmwareError, Result};

/// ROS 2 QoS of the pose, point and `/tf` publishers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Ros2Qos {
    /// ROS 2's sensor-data profile: best effort, volatile, keep last 5.
    #[default]
    SensorData,
    /// Reliable, volatile, keep last 5; a full send window drops the sample (counted).
    Reliable,
}

/// `[outputs.ros2]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2Config {
    /// Off by default.
    #[serde(default)]
    pub enabled: bool,
    /// DDS domain (`ROS_DOMAIN_ID`), 0..=232.
    #[serde(default)]
    pub domain_id: u32,
    /// Namespace of the topics (`<namespace>/<tool>/pose`, `<namespace>/led/point`).
    #[serde(default = "default_namespace")]
    pub namespace: String,
    /// The node's name.
    #[serde(default = "default_node")]
    pub node_name: String,
    /// QoS profile of the publishers.
    #[serde(default)]
    pub qos: Ros2Qos,
    /// Tools to publish, by name in the parameter set; empty: every tool.
    #[serde(default)]
    pub tools: Vec<String>,
}

fn default_namespace() -> String {
    "/irtrack".into()
}
fn default_node() -> String {
    "irtrackd".into()
}

impl Default for Ros2Config {
    fn default() -> Self {
        Self {
            enabled: false,
            domain_id: 0,
            namespace: default_namespace(),
            node_name: default_node(),
            qos: Ros2Qos::default(),
            tools: Vec::new(),
        }
    }
}

/// Highest domain id: DDS's port mapping (7400 + 250 × domain + offsets) must stay below
/// 65536, which ROS 2 documents as 0..=232 on Linux.
pub const MAX_DOMAIN_ID: u32 = 232;

fn bad(reason: String) -> FirmwareError {
    FirmwareError::Config {
        reason: format!("outputs.ros2.{reason}"),
    }
}

/// A ROS name token: letters, digits and `_`, not starting with a digit.
fn is_token(s: &str) -> bool {
    !s.is_empty()
        && !s.starts_with(|c: char| c.is_ascii_digit())
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// A tool name as a ROS name token: characters outside `[A-Za-z0-9_]` become `_`, a leading
/// digit gets a `t` in front.
pub fn token_of(name: &str) -> String {
    // One rule for live topics and recordings (irtrack_interop::mcap uses it too).
    irtrack_interop::ros2msg::ros_token(name)
}

impl Ros2Config {
    /// Checks the table (errors name the key). Tool names are checked against the parameter
    /// set by [`Ros2Config::check_tools`].
    pub fn validate(&self) -> Result<()> {
        if !self.enabled {
            return Ok(());
        }
        if !cfg!(feature = "ros2") {
            return Err(FirmwareError::Config {
                reason: "outputs.ros2: irtrackd was built without the `ros2` feature".into(),
            });
        }
        if self.domain_id > MAX_DOMAIN_ID {
            return Err(bad(format!(
                "domain_id: {} is not a DDS domain id (0..={MAX_DOMAIN_ID})",
                self.domain_id
            )));
        }
        let ns = self.namespace.trim_end_matches('/');
        if !self.namespace.starts_with('/') || (!ns.is_empty() && !ns[1..].split('/').all(is_token)) {
            return Err(bad(format!(
                "namespace: {:?} is not an absolute ROS namespace (`/` then tokens of letters, digits and `_` separated by `/`)",
                self.namespace
            )));
        }
        if !is_token(&self.node_name) {
            return Err(bad(format!(
                "node_name: {:?} is not a ROS node name (letters, digits and `_`)",
                self.node_name
            )));
        }
        Ok(())
    }

    /// Every name in `tools` must name a tool of the parameter set (`available`).
    pub fn check_tools<'a>(&self, available: impl Iterator<Item = &'a str> + Clone) -> Result<()> {
        for want in &self.tools {
            if !available.clone().any(|t| t == want) {
                let names: Vec<&str> = available.clone().collect();
                return Err(bad(format!(
                    "tools: unknown tool {want:?}; the parameter set has {}",
                    if names.is_empty() {
                        "no tools".to_string()
                    } else {
                        names.join(", ")
                    }
                )));
            }
        }
        Ok(())
    }

    /// The namespace without a trailing `/` (`""` for the root).
    pub fn namespace_prefix(&self) -> &str {
        self.namespace.trim_end_matches('/')
    }
}

#[cfg(feature = "ros2")]
pub use imp::Ros2Output;

#[cfg(feature = "ros2")]
mod imp {
    use std::future::Future;
    use std::sync::Arc;
    use std::sync::atomic::Ordering;
    use std::time::{Duration, Instant};

    use irtrack_core::camera::RigidTransform;
    use irtrack_core::stream::PositionRecord;
    use irtrack_interop::ros2msg::{FRAME_CAMERA0, FRAME_WORLD};
    use irtrack_interop::ros2types::{
        Header, POINT_FIELD_FLOAT32, POINT_FIELD_UINT32, Point, PointCloud2, PointField, PointStamped, Pose,
        PoseStamped, Quaternion, TFMessage, Time, Transform, TransformStamped,
    };
    use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
    use ros2_client::qos::{Durability, History, Reliability, WhenFull};
    use ros2_client::{
        Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher, QosProfile,
        WriteError,
    };
    use tokio::sync::watch;

    use super::{Ros2Config, Ros2Qos, token_of};
    use crate::engine::ParamsHandle;
    use crate::error::{FirmwareError, Result};
    use crate::outputs::OutputStats;
    use crate::outputs::scene::{Axes, Models, SceneBuilder, SceneFrame};
    use crate::status::SharedStatus;

    const R: Ordering = Ordering::Relaxed;
    /// Child frame of the single LED in `/tf`.
    const FRAME_LED: &str = "irtrack_led";
    /// Topic leaf of the loose LEDs' cloud: `<namespace>/loose/points`.
    const LOOSE_TOPIC: &str = "loose/points";
    /// Bytes per loose LED in the cloud: x, y, z (float32, metres) and `loose_id` (uint32).
    const LOOSE_POINT_STEP: u32 = 16;

    fn err(what: &'static str) -> impl FnOnce(String) -> FirmwareError {
        move |reason| FirmwareError::Output { what, reason }
    }

    /// A started DDS participant and node, not yet publishing.
    pub struct Ros2Output {
        cfg: Ros2Config,
        node: Node,
        tools: Option<watch::Receiver<crate::engine::ToolSet>>,
    }

    /// The publishers of one model (a tool, or the single LED).
    struct ModelPubs {
        /// Model id (as [`crate::outputs::scene::ModelDef::id`]).
        id: u32,
        child_frame: String,
        pose: Option<Publisher<PoseStamped>>,
        point: Option<Publisher<PointStamped>>,
    }

    impl Ros2Output {
        /// Joins the DDS domain and creates the node (a bad domain or a socket that cannot be
        /// opened fails here).
        pub fn start(cfg: &Ros2Config) -> Result<Self> {
            cfg.validate()?;
            let domain = u16::try_from(cfg.domain_id).unwrap_or(u16::MAX);
            let context = Context::with_options(ContextOptions::new().domain_id(domain)).map_err(|e| {
                FirmwareError::Config {
                    reason: format!(
                        "outputs.ros2.domain_id: cannot join DDS domain {}: {e:?}",
                        cfg.domain_id
                    ),
                }
            })?;
            let ns = cfg.namespace_prefix();
            let node_name =
                NodeName::new(if ns.is_empty() { "/" } else { ns }, &cfg.node_name).map_err(|e| {
                    FirmwareError::Config {
                        reason: format!("outputs.ros2.node_name/namespace: {e:?}"),
                    }
                })?;
            // No rosout, no parameter services: this node only publishes.
            let options = NodeOptions::new()
                .enable_rosout(false)
                .start_parameter_services(false);
            let node = context
                .new_node(node_name, options)
                .map_err(|e| err("ROS 2 node")(format!("{e}")))?;
            Ok(Self {
                cfg: cfg.clone(),
                node,
                tools: None,
            })
        }

        /// Publishes every tool's pose from the loop's per-tool slot.
        pub fn with_tools(mut self, tools: Option<watch::Receiver<crate::engine::ToolSet>>) -> Self {
            self.tools = tools;
            self
        }

        /// Publishes every record the slot shows until `shutdown`. Runs on a thread of its own
        /// (publishing is a blocking call into the DDS stack), driven by `rt`.
        pub fn spawn(
            self,
            rt: tokio::runtime::Handle,
            slot: watch::Receiver<Option<PositionRecord>>,
            params: Arc<ParamsHandle>,
            status: Arc<SharedStatus>,
            stats: Arc<OutputStats>,
            shutdown: impl Future<Output = ()> + Send + 'static,
        ) -> Result<std::thread::JoinHandle<()>> {
            std::thread::Builder::new()
                .name("irtrackd-ros2".into())
                .spawn(move || {
                    let mut p = Publishing::new(self, params, status, stats);
                    rt.block_on(p.run(slot, shutdown));
                })
                .map_err(|e| FirmwareError::Thread {
                    what: "irtrackd-ros2",
                    reason: e.to_string(),
                })
        }
    }

    fn qos_of(q: Ros2Qos) -> QosProfile {
        let base = QosProfile::subscription_default().history(History::KeepLast { depth: 5 });
        match q {
            Ros2Qos::SensorData => base.reliability(Reliability::BestEffort),
            // Fail at once when the window is full: the sample is dropped and counted.
            Ros2Qos::Reliable => base.reliability(Reliability::Reliable {
                when_full: WhenFull::Fail,
            }),
        }
    }

    /// `/tf_static`'s QoS in ROS 2: reliable, transient local, keep last 1 (late joiners get
    /// the registration).
    fn static_qos() -> QosProfile {
        QosProfile::subscription_default()
            .reliability(Reliability::Reliable {
                when_full: WhenFull::Fail,
            })
            .durability(Durability::TransientLocal)
            .history(History::KeepLast { depth: 1 })
    }

    struct Publishing {
        cfg: Ros2Config,
        node: Node,
        params: Arc<ParamsHandle>,
        status: Arc<SharedStatus>,
        stats: Arc<OutputStats>,
        generation: u64,
        builder: SceneBuilder,
        scene: SceneFrame,
        models: Vec<ModelPubs>,
        tf: Option<Publisher<TFMessage>>,
        tf_static: Option<Publisher<TFMessage>>,
        /// The loose LEDs' cloud (only while the set has tools).
        loose: Option<Publisher<PointCloud2>>,
        /// cam0_from_world (inverse registration), to give `/tf` in the tracker frame.
        cam0_from_world: Option<(Rotation3<f64>, Vector3<f64>)>,
        offset_ns: i128,
        received: u64,
        last_clients: Instant,
    }

    fn rotation_of(t: &RigidTransform) -> Rotation3<f64> {
        Rotation3::from_matrix_unchecked(Matrix3::from_row_slice(&t.r_row_major))
    }

    fn quat_xyzw(r: &Rotation3<f64>) -> [f64; 4] {
        let q = UnitQuaternion::from_rotation_matrix(r);
        [q.i, q.j, q.k, q.w]
    }

    impl Publishing {
        fn new(
            out: Ros2Output,
            params: Arc<ParamsHandle>,
            status: Arc<SharedStatus>,
            stats: Arc<OutputStats>,
        ) -> Self {
            let wall = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos() as i128);
            Self {
                cfg: out.cfg,
                node: out.node,
                params,
                status,
                stats,
                generation: u64::MAX,
                builder: SceneBuilder::new(Models::default(), Axes::Tracker).with_tools(out.tools),
                scene: SceneFrame::default(),
                models: Vec::new(),
                tf: None,
                tf_static: None,
                loose: None,
                cam0_from_world: None,
                offset_ns: wall - i128::from(crate::clock::monotonic_ns()),
                received: 0,
                last_clients: Instant::now(),
            }
        }

        fn topic_name(&self, model: &str, leaf: &str) -> String {
            format!("{}/{}/{leaf}", self.cfg.namespace_prefix(), token_of(model))
        }

        fn publisher<M: serde::Serialize>(
            &mut self,
            topic: &str,
            package: &str,
            ty: &str,
            qos: &QosProfile,
        ) -> Option<Publisher<M>> {
            let made = Name::parse(topic)
                .map_err(|e| format!("{e:?}"))
                .and_then(|name| {
                    self.node
                        .create_topic(&name, MessageTypeName::new(package, ty), qos)
                        .map_err(|e| format!("{e:?}"))
                })
                .and_then(|t| {
                    self.node
                        .create_publisher(&t, Some(qos.clone()))
                        .map_err(|e| format!("{e:?}"))
                });
            match made {
                Ok(p) => Some(p),
                Err(e) => {
                    tracing::error!(topic, error = %e, "ROS 2 publisher not created");
                    None
                }
            }
        }

        /// (Re)creates the publishers after a parameter swap (allocates; only then).
        fn refresh(&mut self) {
            let generation = self.params.generation();
            if generation == self.generation {
                return;
            }
            self.generation = generation;
            let current = self.params.current();
            let rig = current.as_ref().map(|p| &p.rig);
            let mut models = Models::of_rig(rig);
            if !self.cfg.tools.is_empty() {
                let known: Vec<&str> = models.list.iter().map(|m| m.name.as_str()).collect();
                for want in &self.cfg.tools {
                    if !known.contains(&want.as_str()) {
                        tracing::warn!(tool = %want, "outputs.ros2.tools: the new parameter set has no such tool; not published");
                    }
                }
                models
                    .list
                    .retain(|m| !m.rigid_body || self.cfg.tools.contains(&m.name));
            }
            let qos = super::imp::qos_of(self.cfg.qos);
            if self.tf.is_none() {
                self.tf = self.publisher("/tf", "tf2_msgs", "TFMessage", &qos);
            }
            let mut pubs = Vec::new();
            for m in &models.list {
                if let Some(old) = self
                    .models
                    .iter()
                    .position(|p| p.id == m.id && p.child_frame == child_frame(&m.name, m.rigid_body))
                {
                    pubs.push(self.models.swap_remove(old));
                    continue;
                }
                let (pose, point) = if m.rigid_body {
                    let topic = self.topic_name(&m.name, "pose");
                    (self.publisher(&topic, "geometry_msgs", "PoseStamped", &qos), None)
                } else {
                    let topic = self.topic_name(&m.name, "point");
                    (
                        None,
                        self.publisher(&topic, "geometry_msgs", "PointStamped", &qos),
                    )
                };
                tracing::info!(model = %m.name, "ROS 2 topics for model");
                pubs.push(ModelPubs {
                    id: m.id,
                    child_frame: child_frame(&m.name, m.rigid_body),
                    pose,
                    point,
                });
            }
            self.models = pubs;
            // Loose single LEDs are reported beside tools only.
            let has_tools =
                models.list.iter().any(|m| m.rigid_body) || rig.is_some_and(|r| !r.tools.is_empty());
            if has_tools && self.loose.is_none() {
                let topic = format!("{}/{LOOSE_TOPIC}", self.cfg.namespace_prefix());
                self.loose = self.publisher(&topic, "sensor_msgs", "PointCloud2", &qos);
            } else if !has_tools {
                self.loose = None;
            }
            self.builder.models = models;
            // Registration: robot base → tracker as a static transform.
            self.cam0_from_world = None;
            if let Some(w) = rig.and_then(|r| r.world_from_cam0.as_ref()) {
                let r = rotation_of(w);
                let t = Vector3::from(w.t_mm) / 1e3;
                self.cam0_from_world = Some((r.inverse(), -(r.inverse() * t)));
                if self.tf_static.is_none() {
                    self.tf_static = self.publisher("/tf_static", "tf2_msgs", "TFMessage", &static_qos());
                }
                let msg = TFMessage {
                    transforms: vec![TransformStamped {
                        header: Header {
                            stamp: Time::from_ns(self.wall(crate::clock::monotonic_ns())),
                            frame_id: FRAME_WORLD.into(),
                        },
                        child_frame_id: FRAME_CAMERA0.into(),
                        transform: Transform {
                            translation: Point::from([t.x, t.y, t.z]),
                            rotation: Quaternion::from(quat_xyzw(&r)),
                        },
                    }],
                };
                if let Some(p) = &self.tf_static {
                    match p.publish(msg) {
                        Ok(()) => tracing::info!("ROS 2 /tf_static: robot base → tracker published"),
                        Err(e) => tracing::warn!(error = %describe(&e), "ROS 2 /tf_static not published"),
                    }
                }
            }
        }

        fn wall(&self, mono_ns: u64) -> u64 {
            u64::try_from(i128::from(mono_ns) + self.offset_ns).unwrap_or(0)
        }

        fn sent<M>(&self, r: std::result::Result<(), WriteError<M>>) {
            match r {
                Ok(()) => {
                    self.stats.frames_sent.fetch_add(1, R);
                }
                Err(e) => {
                    let drops = self.stats.send_drops.fetch_add(1, R);
                    if drops.is_multiple_of(1000) {
                        tracing::warn!(error = %describe(&e), drops = drops + 1, "ROS 2 message not published; dropped");
                    }
                }
            }
        }

        fn record(&mut self, rec: &PositionRecord) {
            self.received += 1;
            let published = self.status.published.load(R);
            self.stats
                .slot_skips
                .store(published.saturating_sub(self.received), R);
            self.refresh();
            self.builder.fill(rec, &mut self.scene);
            let stamp = Time::from_ns(self.wall(rec.capture_ts_ns));
            let frame_id = if rec.world_frame {
                FRAME_WORLD
            } else {
                FRAME_CAMERA0
            };
            let mut tf = TFMessage::default();
            // Rigid bodies: one per tool of the set (a loop, so several tools need no change).
            for body in self.scene.bodies.iter().filter(|b| b.tracked) {
                let Some(m) = self.models.iter().find(|m| m.id == body.id) else {
                    continue;
                };
                let pose = Pose {
                    position: Point::from(body.position_m),
                    orientation: Quaternion::from(body.orientation_xyzw),
                };
                if let Some(p) = &m.pose {
                    let msg = PoseStamped {
                        header: Header {
                            stamp,
                            frame_id: frame_id.into(),
                        },
                        pose,
                    };
                    self.sent(p.publish(msg));
                }
                tf.transforms.push(self.tracker_tf(
                    stamp,
                    rec.world_frame,
                    &m.child_frame,
                    body.position_m,
                    body.orientation_xyzw,
                ));
            }
            // The single LED (a model without a rigid body).
            for (model, set) in self.builder.models.list.iter().zip(&self.scene.marker_sets) {
                if model.rigid_body || self.scene.unlabelled_m.is_empty() {
                    continue;
                }
                let Some(m) = self.models.iter().find(|m| m.id == model.id) else {
                    continue;
                };
                let p_m = set.first().copied().unwrap_or([0.0; 3]);
                if let Some(p) = &m.point {
                    let msg = PointStamped {
                        header: Header {
                            stamp,
                            frame_id: frame_id.into(),
                        },
                        point: Point::from(p_m),
                    };
                    self.sent(p.publish(msg));
                }
                tf.transforms.push(self.tracker_tf(
                    stamp,
                    rec.world_frame,
                    &m.child_frame,
                    p_m,
                    [0.0, 0.0, 0.0, 1.0],
                ));
            }
            // Loose single LEDs: one cloud per set, empty when none is tracked (a display
            // then clears the last points instead of freezing them); none when this set's
            // per-tool records were already replaced by a newer set's.
            if let Some(p) = self.loose.as_ref().filter(|_| self.scene.per_tool) {
                let msg = loose_cloud(
                    Header {
                        stamp,
                        frame_id: frame_id.into(),
                    },
                    &self.scene.loose,
                );
                self.sent(p.publish(msg));
            }
            if !tf.transforms.is_empty()
                && let Some(p) = &self.tf
            {
                self.sent(p.publish(tf));
                // Capture → the record's messages handed to the DDS stack.
                self.stats.record_latency(rec.capture_ts_ns);
            }
        }

        /// tracker (camera 0) → child, from a pose in the record's frame.
        fn tracker_tf(
            &self,
            stamp: Time,
            world: bool,
            child: &str,
            p_m: [f64; 3],
            q_xyzw: [f64; 4],
        ) -> TransformStamped {
            let (p, q) = match (world, &self.cam0_from_world) {
                (true, Some((r, t))) => {
                    let p = r * Vector3::from(p_m) + t;
                    let q = UnitQuaternion::from_rotation_matrix(r)
                        * UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                            q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2],
                        ));
                    ([p.x, p.y, p.z], [q.i, q.j, q.k, q.w])
                }
                _ => (p_m, q_xyzw),
            };
            TransformStamped {
                header: Header {
                    stamp,
                    frame_id: FRAME_CAMERA0.into(),
                },
                child_frame_id: child.into(),
                transform: Transform {
                    translation: Point::from(p),
                    rotation: Quaternion::from(q),
                },
            }
        }

        /// Subscriptions matched by the publishers (the output's "clients"), once a second.
        fn count_clients(&mut self) {
            if self.last_clients.elapsed() < Duration::from_secs(1) {
                return;
            }
            self.last_clients = Instant::now();
            let mut n = 0;
            for m in &self.models {
                n += m
                    .pose
                    .as_ref()
                    .map_or(0, |p| p.get_subscription_count(&self.node));
                n += m
                    .point
                    .as_ref()
                    .map_or(0, |p| p.get_subscription_count(&self.node));
            }
            n += self
                .tf
                .as_ref()
                .map_or(0, |p| p.get_subscription_count(&self.node));
            n += self
                .loose
                .as_ref()
                .map_or(0, |p| p.get_subscription_count(&self.node));
            self.stats.clients.store(n as u64, R);
        }

        async fn run(
            &mut self,
            mut slot: watch::Receiver<Option<PositionRecord>>,
            shutdown: impl Future<Output = ()>,
        ) {
            tokio::pin!(shutdown);
            self.refresh();
            tracing::info!(
                domain = self.cfg.domain_id,
                namespace = %self.cfg.namespace,
                qos = ?self.cfg.qos,
                "ROS 2 output started"
            );
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tokio::select! {
                    _ = &mut shutdown => break,
                    changed = slot.changed() => {
                        if changed.is_err() {
                            break;
                        }
                        let rec = *slot.borrow_and_update();
                        if let Some(rec) = rec {
                            self.record(&rec);
                        }
                        self.count_clients();
                    }
                    _ = tick.tick() => self.count_clients(),
                }
            }
            tracing::info!("ROS 2 output stopped");
        }
    }

    /// The loose LEDs as a `PointCloud2`: one row, x y z as float32 metres (0.06 µm steps at
    /// 1 m, far below the tracker's resolution; float32 is what every cloud display reads) and
    /// the stable `loose_id` as uint32, little-endian.
    fn loose_cloud(header: Header, loose: &[crate::outputs::scene::LooseSample]) -> PointCloud2 {
        let field = |name: &str, offset, datatype| PointField {
            name: name.into(),
            offset,
            datatype,
            count: 1,
        };
        let mut data = Vec::with_capacity(loose.len() * LOOSE_POINT_STEP as usize);
        for l in loose {
            for v in l.position_m {
                data.extend_from_slice(&(v as f32).to_le_bytes());
            }
            data.extend_from_slice(&l.loose_id.to_le_bytes());
        }
        let width = loose.len() as u32;
        PointCloud2 {
            header,
            height: 1,
            width,
            fields: vec![
                field("x", 0, POINT_FIELD_FLOAT32),
                field("y", 4, POINT_FIELD_FLOAT32),
                field("z", 8, POINT_FIELD_FLOAT32),
                field("loose_id", 12, POINT_FIELD_UINT32),
            ],
            is_bigendian: false,
            point_step: LOOSE_POINT_STEP,
            row_step: LOOSE_POINT_STEP * width,
            data,
            is_dense: true,
        }
    }

    fn child_frame(name: &str, rigid_body: bool) -> String {
        if rigid_body {
            format!("irtrack_{}", token_of(name))
        } else {
            FRAME_LED.into()
        }
    }

    fn describe<M>(e: &WriteError<M>) -> String {
        match e {
            WriteError::Serialization { reason, .. } => format!("serialization: {reason}"),
            WriteError::Poisoned { reason, .. } => format!("poisoned: {reason}"),
            WriteError::Io(e) => format!("I/O: {e}"),
            WriteError::WouldBlock { .. } => "send window full".into(),
            WriteError::Internal { reason } => format!("internal: {reason}"),
            WriteError::Middleware { reason, .. } => format!("middleware: {reason}"),
            #[allow(unreachable_patterns)]
            _ => "write failed".into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(toml_text: &str) -> Ros2Config {
        toml::from_str(toml_text).unwrap()
    }

    #[test]
    fn bad_settings_name_the_key() {
        let e = cfg("enabled = true\ndomain_id = 233")
            .validate()
            .unwrap_err()
            .to_string();
        if cfg!(feature = "ros2") {
            assert!(e.contains("outputs.ros2.domain_id") && e.contains("233"), "{e}");
            let e = cfg("enabled = true\nnamespace = \"irtrack\"")
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains("outputs.ros2.namespace"), "{e}");
            let e = cfg("enabled = true\nnamespace = \"/a b\"")
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains("outputs.ros2.namespace"), "{e}");
            let e = cfg("enabled = true\nnode_name = \"9x\"")
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains("outputs.ros2.node_name"), "{e}");
            cfg("enabled = true\nnamespace = \"/cell_1/irtrack\"")
                .validate()
                .unwrap();
            cfg("enabled = true\nnamespace = \"/\"").validate().unwrap();
        } else {
            assert!(e.contains("without the `ros2` feature"), "{e}");
        }
        assert!(toml::from_str::<Ros2Config>("qos = \"fast\"").is_err());
        assert!(toml::from_str::<Ros2Config>("domian_id = 1").is_err());
        // Off: nothing is checked.
        cfg("domain_id = 999").validate().unwrap();
    }

    #[test]
    fn unknown_tools_are_named_with_the_ones_available() {
        let c = cfg("enabled = true\ntools = [\"probe4\", \"wand\"]");
        let tools = ["probe4", "pointer"];
        let e = c.check_tools(tools.iter().copied()).unwrap_err().to_string();
        assert!(e.contains("\"wand\"") && e.contains("probe4, pointer"), "{e}");
        cfg("enabled = true\ntools = [\"probe4\"]")
            .check_tools(tools.iter().copied())
            .unwrap();
        let e = c.check_tools([].iter().copied()).unwrap_err().to_string();
        assert!(e.contains("no tools"), "{e}");
    }

    #[test]
    fn tool_names_become_ros_tokens() {
        assert_eq!(token_of("probe4"), "probe4");
        assert_eq!(token_of("my tool-2"), "my_tool_2");
        assert_eq!(token_of("3d"), "t3d");
    }
}
