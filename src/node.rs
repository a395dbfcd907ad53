//! The ROS 2 node: DDS entities (`ros2-client` / `rustdds`), threads and publishing.
//!
//! Threads, data flowing one way:
//! * **receiver**: takes `sensor_msgs/Image` samples from `image` (best-effort, keep-last 1),
//!   rejects bad ones (counted, throttled warning) and puts the good one in a one-frame slot;
//!   a frame still in the slot is replaced and counted as dropped, so frames never queue;
//! * **worker**: takes the slot's frame, runs [`Processor::process`] and publishes every
//!   output with the image stamp;
//! * **spinner**: ros2-client's graph bookkeeping (discovery, `/clock`);
//! * **parameters**: serves the parameter services (`ros2 param get/set/list/describe`) in the
//!   request/reply mapping of the middleware named by `RMW_IMPLEMENTATION`
//!   ([`crate::param_services`]);
//! * **main**: publishes `/diagnostics` about once a second and watches whether anyone
//!   subscribes to `~/debug_image`.
//!
//! Parameter changes are validated ([`NodeParams::with`], rejected with a reason) and take
//! effect on the next frame.

use crate::diagnostics::{Stats, Throttle};
use crate::messages::{
    DiagnosticArray, Image, MarkerPoseArray, PoseStamped, RosMessage, TfMessage,
};
use crate::param_services::{mapping_for_rmw, ParameterAccess, ParameterServices};
use crate::params::NodeParams;
use crate::processing::{annotate, FrameOutput, Processor};
use crate::ros_args::{fully_qualified, RosArgs};
use log::{error, info, warn};
use ros2_client::qos::{Durability, History, Reliability, WhenFull};
use ros2_client::{
    Context, ContextOptions, Name, Node, NodeName, NodeOptions, ParameterValue, Publisher,
    QosProfile, Subscription,
};
use std::collections::btree_map::Entry;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Node name when `__node:=` is not given.
pub const DEFAULT_NODE_NAME: &str = "vernier_detector";

/// How often `/diagnostics` is published.
const DIAGNOSTICS_PERIOD: Duration = Duration::from_secs(1);
/// At most one warning of a kind per this period.
const WARN_PERIOD: Duration = Duration::from_secs(5);

/// Usage text for `--help`.
pub const USAGE: &str = "\
vernier_ros detector: ROS 2 node measuring marker poses in sensor_msgs/Image frames.

usage: detector [--help] --ros-args [--params-file FILE] [-p name:=value]... [-r from:=to]...
                [-r __ns:=/namespace] [-r __node:=name] [--log-level LEVEL]

Subscribes: image (sensor_msgs/Image)
Publishes:  ~/markers (vernier_ros/MarkerPoseArray), ~/marker_<id>/pose and
            ~/relative/marker_<a>_<b>/pose (geometry_msgs/PoseStamped), /tf,
            /diagnostics, ~/debug_image (only while subscribed)
Parameters: see params/detector.yaml. The DDS domain is ROS_DOMAIN_ID (default 0).";

/// State shared by the threads.
struct Shared {
    /// Current parameters and their generation (incremented on every accepted change).
    params: Mutex<(NodeParams, u64)>,
    stats: Mutex<Stats>,
    /// The newest frame not yet taken by the worker.
    slot: Mutex<Option<Image>>,
    slot_filled: Condvar,
    /// Someone subscribes to `~/debug_image`.
    debug_wanted: AtomicBool,
}

/// Locks a mutex, recovering the data if a thread panicked while holding it (the counters
/// and parameters stay meaningful).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Quality of service of the image subscription: sensor data, newest frame only.
fn image_qos() -> QosProfile {
    QosProfile::subscription_default()
        .reliability(Reliability::BestEffort)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 1 })
}

/// Quality of service of the outputs: reliable, never blocking the worker.
fn output_qos(depth: usize) -> QosProfile {
    QosProfile::publisher_default()
        .reliability(Reliability::Reliable {
            when_full: WhenFull::Fail,
        })
        .history(History::KeepLast { depth })
}

/// Runs the node with the process arguments (without the program name) until killed.
pub fn run(argv: Vec<String>) -> Result<(), String> {
    let args = RosArgs::parse(argv).map_err(|e| e.to_string())?;
    if args.other.iter().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}");
        return Ok(());
    }
    if !args.other.is_empty() {
        return Err(format!(
            "unexpected arguments {:?} (node arguments go after --ros-args; see --help)",
            args.other
        ));
    }
    init_logging(args.log_level.as_deref());

    let node_name = args
        .node_name
        .clone()
        .unwrap_or_else(|| DEFAULT_NODE_NAME.into());
    let namespace = args.namespace.clone().unwrap_or_else(|| "/".into());
    let overrides = args
        .parameter_overrides(&namespace, &node_name)
        .map_err(|e| e.to_string())?;
    let params = NodeParams::from_overrides(&overrides).map_err(|e| {
        if args.params_files.is_empty() {
            format!(
                "{e} (start it with `--ros-args --params-file params/detector.yaml`, or set \
                 parameters with `--ros-args -p name:=value`; see --help)"
            )
        } else {
            e
        }
    })?;
    let processor = Processor::new(params.clone(), 0)?;
    let shared = Arc::new(Shared {
        params: Mutex::new((params.clone(), 0)),
        stats: Mutex::new(Stats::default()),
        slot: Mutex::new(None),
        slot_filled: Condvar::new(),
        debug_wanted: AtomicBool::new(false),
    });

    let domain_id = match std::env::var("ROS_DOMAIN_ID") {
        Ok(text) if !text.trim().is_empty() => text
            .trim()
            .parse::<u16>()
            .map_err(|_| format!("ROS_DOMAIN_ID `{text}` is not a domain number"))?,
        _ => 0,
    };
    let context = Context::with_options(ContextOptions::new().domain_id(domain_id))
        .map_err(|e| format!("cannot start DDS: {e:?}"))?;
    let mut options = NodeOptions::new()
        .enable_rosout(true)
        // Served by crate::param_services instead, which also speaks Cyclone's mapping.
        .start_parameter_services(false);
    for (name, value) in params.values() {
        options = options.declare_parameter(name, value.clone());
    }
    let for_validator = Arc::clone(&shared);
    let for_action = Arc::clone(&shared);
    options = options
        .parameter_validator(Box::new(move |name, value| {
            lock(&for_validator.params).0.with(name, value).map(|_| ())
        }))
        .parameter_set_action(Box::new(move |name, value| {
            apply_parameter(&for_action, name, value)
        }));
    let mut node = context
        .new_node(
            NodeName::new(&namespace, &node_name).map_err(|e| e.to_string())?,
            options,
        )
        .map_err(|e| format!("cannot create node: {e:?}"))?;
    let fq_name = fully_qualified(&namespace, &node_name);
    info!("node {fq_name} on DDS domain {domain_id}");

    let topic = |name: &str| args.resolve_topic(name, &namespace, &node_name);
    let image_topic = topic("image");
    let subscription: Subscription<Image> = {
        let t = create_topic::<Image>(&node, &image_topic, &image_qos())?;
        node.create_subscription(&t, Some(image_qos()))
            .map_err(|e| format!("cannot subscribe to {image_topic}: {e:?}"))?
    };
    let names = TopicNames {
        args: args.clone(),
        namespace: namespace.clone(),
        node_name: node_name.clone(),
    };
    let mut publishers = Publishers {
        markers: publisher(&mut node, &topic("~/markers"), output_qos(10))?,
        tf: publisher(&mut node, &topic("/tf"), output_qos(100))?,
        debug: publisher(&mut node, &topic("~/debug_image"), output_qos(1))?,
        poses: BTreeMap::new(),
        relative: BTreeMap::new(),
    };
    // Configured IDs and pairs get their publishers now, so that subscribers are matched
    // before the first frame (samples sent before matching are lost).
    for id in &params.marker_ids {
        publishers.pose(*id, &mut node, &names)?;
    }
    for pair in &params.relative_pairs {
        publishers.relative_pose(*pair, &mut node, &names)?;
    }
    let diagnostics: Publisher<DiagnosticArray> =
        publisher(&mut node, &topic("/diagnostics"), output_qos(10))?;
    info!(
        "waiting for frames (sensor_msgs/Image) on {image_topic}; publishing on {}",
        topic("~/markers")
    );

    let rmw = std::env::var("RMW_IMPLEMENTATION").ok();
    let parameter_services =
        ParameterServices::create(&mut node, &fq_name, mapping_for_rmw(rmw.as_deref()))?;
    let spinner = node
        .spinner()
        .map_err(|e| format!("cannot start the ROS 2 spinner: {e:?}"))?;
    std::thread::Builder::new()
        .name("spinner".into())
        .spawn(move || {
            if let Err(e) = futures::executor::block_on(spinner.spin()) {
                error!("spinner stopped: {e:?}");
            }
        })
        .map_err(|e| e.to_string())?;

    let node = Arc::new(Mutex::new(node));
    {
        let access = NodeParameters {
            node: Arc::clone(&node),
            shared: Arc::clone(&shared),
        };
        std::thread::Builder::new()
            .name("parameters".into())
            .spawn(move || parameter_services.serve(&access))
            .map_err(|e| e.to_string())?;
    }
    {
        let shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("receiver".into())
            .spawn(move || receive_loop(subscription, &shared))
            .map_err(|e| e.to_string())?;
    }
    {
        let shared = Arc::clone(&shared);
        let node = Arc::clone(&node);
        std::thread::Builder::new()
            .name("worker".into())
            .spawn(move || work_loop(processor, publishers, &shared, &node, &names))
            .map_err(|e| e.to_string())?;
    }

    // Main thread: diagnostics and debug-image demand.
    let debug_topic = topic("~/debug_image");
    let mut window_start = Instant::now();
    loop {
        std::thread::sleep(DIAGNOSTICS_PERIOD);
        let wanted = lock(&node).subscription_count(&debug_topic) > 0;
        shared.debug_wanted.store(wanted, Ordering::Relaxed);
        let report = lock(&shared.stats).report(&fq_name, window_start.elapsed());
        window_start = Instant::now();
        if let Err(e) = diagnostics.publish(report) {
            warn!("cannot publish diagnostics: {e:?}");
        }
    }
}

/// Validates and applies one parameter change (called by the parameter store, both for the
/// initial values and for `ros2 param set`).
fn apply_parameter(shared: &Shared, name: &str, value: &ParameterValue) -> Result<(), String> {
    let mut guard = lock(&shared.params);
    let updated = guard.0.with(name, value)?;
    if updated != guard.0 {
        info!("parameter {name} = {value:?} (applies from the next frame)");
        guard.0 = updated;
        guard.1 += 1;
    }
    Ok(())
}

/// The parameter services' view of the node: ros2-client's store (declared parameters, our
/// validator and set action, `/parameter_events`) plus our validation for atomic sets.
struct NodeParameters {
    node: Arc<Mutex<Node>>,
    shared: Arc<Shared>,
}

impl ParameterAccess for NodeParameters {
    fn get(&self, name: &str) -> Option<ParameterValue> {
        lock(&self.node).get_parameter(name)
    }
    fn names(&self) -> Vec<String> {
        lock(&self.node).list_parameters()
    }
    fn set(&self, name: &str, value: ParameterValue) -> Result<(), String> {
        // Lock order: node, then params (inside the validator); the worker never holds params
        // while taking the node.
        lock(&self.node).set_parameter(name, value)
    }
    fn validate_all(&self, changes: &[(String, ParameterValue)]) -> Result<(), String> {
        let mut params = lock(&self.shared.params).0.clone();
        for (name, value) in changes {
            params = params.with(name, value)?;
        }
        Ok(())
    }
}

fn init_logging(level: Option<&str>) {
    let filter = match level {
        Some("debug") => log::LevelFilter::Debug,
        Some("warn") => log::LevelFilter::Warn,
        Some("error") | Some("fatal") => log::LevelFilter::Error,
        _ => log::LevelFilter::Info,
    };
    // The node's own messages at `level`; the DDS stack is chatty at info: warnings only,
    // unless RUST_LOG says otherwise.
    let mut builder = env_logger::Builder::new();
    builder
        .filter_level(log::LevelFilter::Warn)
        .filter_module("vernier_ros", filter)
        .filter_module("detector", filter)
        .parse_env("RUST_LOG");
    // A second initialisation (tests) is harmless.
    builder.try_init().unwrap_or(());
}

fn create_topic<T: RosMessage>(
    node: &Node,
    absolute_name: &str,
    qos: &QosProfile,
) -> Result<ros2_client::dds::rustdds::Topic, String> {
    let name = Name::parse(absolute_name)
        .map_err(|e| format!("invalid topic name {absolute_name}: {e}"))?;
    node.create_topic(&name, T::type_name(), qos)
        .map_err(|e| format!("cannot create topic {absolute_name}: {e:?}"))
}

fn publisher<T: RosMessage>(
    node: &mut Node,
    absolute_name: &str,
    qos: QosProfile,
) -> Result<Publisher<T>, String> {
    let topic = create_topic::<T>(node, absolute_name, &qos)?;
    node.create_publisher(&topic, Some(qos))
        .map_err(|e| format!("cannot publish on {absolute_name}: {e:?}"))
}

/// Takes image samples, rejects bad ones, keeps only the newest good one in the slot.
fn receive_loop(subscription: Subscription<Image>, shared: &Shared) {
    let mut bad_warning = Throttle::new(WARN_PERIOD);
    loop {
        let sample = futures::executor::block_on(subscription.async_take());
        let reason = match sample {
            Ok((image, _info)) => match crate::processing::check_image(&image) {
                Ok(_) => {
                    lock(&shared.stats).received += 1;
                    let replaced = lock(&shared.slot).replace(image).is_some();
                    if replaced {
                        lock(&shared.stats).dropped += 1;
                    }
                    shared.slot_filled.notify_one();
                    continue;
                }
                Err(bad) => bad.0,
            },
            Err(ros2_client::ReadError::Closed) => {
                error!("image subscription closed");
                return;
            }
            Err(e) => format!("undecodable message: {e}"),
        };
        {
            let mut stats = lock(&shared.stats);
            stats.bad_messages += 1;
            stats.last_bad_reason.clone_from(&reason);
        }
        if let Some(held_back) = bad_warning.allow(Instant::now()) {
            warn!("bad image message ignored: {reason} ({held_back} more since the last warning)");
        }
    }
}

/// Output publishers; per-marker and per-pair ones are created on first use.
struct Publishers {
    markers: Publisher<MarkerPoseArray>,
    tf: Publisher<TfMessage>,
    debug: Publisher<Image>,
    poses: BTreeMap<u64, Publisher<PoseStamped>>,
    relative: BTreeMap<(u64, u64), Publisher<PoseStamped>>,
}

impl Publishers {
    /// The publisher of `~/marker_<id>/pose`, created on first use.
    fn pose(
        &mut self,
        id: u64,
        node: &mut Node,
        names: &TopicNames,
    ) -> Result<&Publisher<PoseStamped>, String> {
        Ok(match self.poses.entry(id) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => {
                let name = names.resolve(&format!("~/marker_{id}/pose"));
                e.insert(publisher(node, &name, output_qos(10))?)
            }
        })
    }

    /// The publisher of `~/relative/marker_<a>_<b>/pose`, created on first use (ROS name
    /// tokens cannot start with a digit, hence `marker_`).
    fn relative_pose(
        &mut self,
        (a, b): (u64, u64),
        node: &mut Node,
        names: &TopicNames,
    ) -> Result<&Publisher<PoseStamped>, String> {
        Ok(match self.relative.entry((a, b)) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => {
                let name = names.resolve(&format!("~/relative/marker_{a}_{b}/pose"));
                e.insert(publisher(node, &name, output_qos(10))?)
            }
        })
    }
}

/// What the worker needs to name topics created on the fly.
struct TopicNames {
    args: RosArgs,
    namespace: String,
    node_name: String,
}

impl TopicNames {
    fn resolve(&self, name: &str) -> String {
        self.args
            .resolve_topic(name, &self.namespace, &self.node_name)
    }
}

/// Takes the newest frame, processes it, publishes; rebuilds the detector on parameter
/// changes and applies `max_rate`.
fn work_loop(
    mut processor: Processor,
    mut publishers: Publishers,
    shared: &Shared,
    node: &Mutex<Node>,
    names: &TopicNames,
) {
    let mut not_found_warning = Throttle::new(WARN_PERIOD);
    let mut publish_warning = Throttle::new(WARN_PERIOD);
    let mut last_start: Option<Instant> = None;
    loop {
        let image = {
            let mut slot = lock(&shared.slot);
            loop {
                if let Some(image) = slot.take() {
                    break image;
                }
                slot = shared
                    .slot_filled
                    .wait(slot)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
            }
        };
        let start = Instant::now();
        {
            let guard = lock(&shared.params);
            if guard.1 != processor.generation() {
                if let Err(e) = processor.update(guard.0.clone(), guard.1) {
                    // Validated before acceptance; only a vanished pattern file gets here.
                    warn!("keeping the previous detector: {e}");
                }
            }
        }
        let max_rate = processor.params().max_rate;
        if max_rate > 0.0 {
            if let Some(last) = last_start {
                if start.duration_since(last).as_secs_f64() < 1.0 / max_rate {
                    lock(&shared.stats).rate_limited += 1;
                    continue;
                }
            }
        }
        last_start = Some(start);
        let (output, grey) = match processor.process(&image) {
            Ok(done) => done,
            Err(bad) => {
                // check_image passed in the receiver, so conversion cannot fail; count it anyway.
                let mut stats = lock(&shared.stats);
                stats.bad_messages += 1;
                stats.last_bad_reason = bad.0;
                continue;
            }
        };
        if let Some(reason) = &output.detect_error {
            if let Some(held_back) = not_found_warning.allow(start) {
                warn!("no marker found: {reason} ({held_back} more since the last warning)");
            }
        }
        let mut failures = publish(&output, &mut publishers, node, names, processor.params());
        // The annotated image costs a copy of the frame: only while someone subscribes.
        if shared.debug_wanted.load(Ordering::Relaxed) {
            let debug = annotate(&grey, &output.raw, &output.markers.header);
            if let Err(e) = publishers.debug.publish(debug) {
                failures.push(format!("debug image: {e:?}"));
            }
        }
        {
            let mut stats = lock(&shared.stats);
            stats.record_processing(start.elapsed());
            if output.detect_error.is_some() {
                stats.not_found += 1;
            }
        }
        if let Some(first) = failures.first() {
            if let Some(held_back) = publish_warning.allow(start) {
                warn!("publishing failed: {first} ({held_back} more since the last warning)");
            }
        }
    }
}

/// Publishes one frame's outputs; returns the failures.
fn publish(
    output: &FrameOutput,
    publishers: &mut Publishers,
    node: &Mutex<Node>,
    names: &TopicNames,
    params: &NodeParams,
) -> Vec<String> {
    let mut failures = Vec::new();
    // Per-marker poses before the array: a controller reading the array sees them all sent.
    for (id, pose) in &output.poses {
        let result = match publishers.poses.get(id) {
            Some(p) => p.publish(pose.clone()).map_err(|e| format!("{e:?}")),
            None => publishers
                .pose(*id, &mut lock(node), names)
                .and_then(|p| p.publish(pose.clone()).map_err(|e| format!("{e:?}"))),
        };
        if let Err(e) = result {
            failures.push(format!("marker {id} pose: {e}"));
        }
    }
    for (pair, pose) in &output.relative {
        let result = match publishers.relative.get(pair) {
            Some(p) => p.publish(pose.clone()).map_err(|e| format!("{e:?}")),
            None => publishers
                .relative_pose(*pair, &mut lock(node), names)
                .and_then(|p| p.publish(pose.clone()).map_err(|e| format!("{e:?}"))),
        };
        if let Err(e) = result {
            failures.push(format!("relative pose {}:{}: {e}", pair.0, pair.1));
        }
    }
    if params.publish_tf && !output.tf.transforms.is_empty() {
        if let Err(e) = publishers.tf.publish(output.tf.clone()) {
            failures.push(format!("/tf: {e:?}"));
        }
    }
    if let Err(e) = publishers.markers.publish(output.markers.clone()) {
        failures.push(format!("markers: {e:?}"));
    }
    failures
}
