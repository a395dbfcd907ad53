//! The ROS 2 node: DDS entities (`ros2-client` / `rustdds`), threads and publishing.
//!
//! Threads, data flowing one way:
//! * **receiver**: takes `sensor_msgs/Image` samples from `image` (or
//!   `sensor_msgs/CompressedImage` from `image/compressed` with `image_transport:=compressed`;
//!   QoS from `image_qos` and `qos_overrides`), rejects bad ones (counted, throttled warning)
//!   and puts the good one in a one-frame slot; a frame still in the slot is replaced and
//!   counted as dropped, so frames never queue;
//! * **worker**: takes the slot's frame, decompresses it if needed, runs
//!   [`Processor::process`] and publishes every output with the image stamp;
//! * **spinner**: ros2-client's graph bookkeeping (discovery, `/clock`);
//! * **parameters**: serves the parameter services (`ros2 param get/set/list/describe`) in the
//!   request/reply mapping of the middleware named by `RMW_IMPLEMENTATION`
//!   ([`crate::param_services`]);
//! * **main**: publishes `/diagnostics` about once a second (sliding window, stamped with the
//!   node's clock: `/clock` under `use_sim_time`) and watches whether anyone subscribes to
//!   `~/debug_image`.
//!
//! Warnings and errors also go to `/rosout` (`RosoutLogger`).
//!
//! Parameter changes are validated ([`NodeParams::with`], rejected with a reason) and take
//! effect on the next frame.

use crate::diagnostics::{Event, Stats, Throttle};
use crate::discovery::Discovery;
use crate::messages::{
    Clock, CompressedImage, Detection3DArray, DiagnosticArray, Image, MarkerPoseArray, PoseStamped,
    PoseWithCovarianceStamped, RosType, TfMessage, Time,
};
use crate::param_services::{mapping_for_rmw, ParameterAccess, ParameterServices};
use crate::params::{
    ImageQos, NodeParams, QosDurability, QosHistory, QosReliability, StartupParams,
};
use crate::processing::{annotate, FrameOutput, Processor, DEFAULT_CAMERA_FRAME};
use crate::ros_args::{fully_qualified, RosArgs};
use log::{error, info, warn};
use ros2_client::dds::rustdds::TopicKind;
use ros2_client::qos::{Durability, History, Reliability, WhenFull};
use ros2_client::ros2::{policy, QosPolicies, QosPolicyBuilder};
use ros2_client::{
    Context, MessageTypeName, Name, Node, NodeName, NodeOptions, ParameterValue, Publisher,
    QosProfile, Subscription,
};
use ros2_client::{NodeLoggingHandle, RosoutRaw};
use std::collections::btree_map::Entry;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

/// Node name when `__node:=` is not given.
pub const DEFAULT_NODE_NAME: &str = "vernier_detector";

/// How often `/diagnostics` is published.
const DIAGNOSTICS_PERIOD: Duration = Duration::from_secs(1);
/// At most one warning of a kind per this period.
const WARN_PERIOD: Duration = Duration::from_secs(5);
/// At most one `~/debug_image` per this period: an annotated frame is for eyes, and each one
/// is megabytes on the wire.
const DEBUG_IMAGE_PERIOD: Duration = Duration::from_millis(100);
/// Most `~/debug_image` frames the writer holds unacknowledged (see [`bounded_publisher`]).
const DEBUG_IMAGE_WINDOW: i32 = 4;

/// Usage text for `--help`.
pub const USAGE: &str = "\
vernier_ros detector: ROS 2 node measuring marker poses in sensor_msgs/Image frames.

usage: detector [--help] --ros-args [--params-file FILE] [-p name:=value]... [-r from:=to]...
                [-r __ns:=/namespace] [-r __node:=name] [--log-level LEVEL]

Subscribes: image (sensor_msgs/Image), or image/compressed (sensor_msgs/CompressedImage)
            with -p image_transport:=compressed
Publishes:  ~/detections (vision_msgs/Detection3DArray), ~/markers
            (vernier_ros/MarkerPoseArray), ~/marker_<id>/pose (geometry_msgs/PoseStamped),
            ~/marker_<id>/pose_with_covariance (geometry_msgs/PoseWithCovarianceStamped),
            ~/relative/marker_<a>_<b>/pose, /tf, /diagnostics, /rosout,
            ~/debug_image (only while subscribed, at most 10 Hz)
Parameters: see params/detector.yaml; also use_sim_time and
            qos_overrides./<image topic>.subscription.reliability|history|depth|durability.
            The DDS domain is ROS_DOMAIN_ID (default 0); ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
            or ROS_LOCALHOST_ONLY=1 keeps discovery on the loopback interface (OFF and
            ROS_STATIC_PEERS are not supported).";

/// State shared by the threads.
struct Shared {
    /// Current parameters and their generation (incremented on every accepted change).
    params: Mutex<(NodeParams, u64)>,
    stats: Mutex<Stats>,
    /// The newest frame not yet taken by the worker.
    slot: Mutex<Option<Frame>>,
    slot_filled: Condvar,
    /// Someone subscribes to `~/debug_image`.
    debug_wanted: AtomicBool,
    /// The latest `/clock` time (zero until one arrives, as in rclcpp).
    sim_time: Mutex<Time>,
}

/// An input message as received, with its arrival time (for the latency).
struct Frame {
    message: Input,
    arrived: Instant,
}

/// The two input transports.
enum Input {
    Raw(Image),
    Compressed(CompressedImage),
}

/// Locks a mutex, recovering the data if a thread panicked while holding it (the counters
/// and parameters stay meaningful).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// The image subscription's QoS profile (`image_qos`, `qos_overrides`).
fn image_qos(qos: ImageQos) -> QosProfile {
    let profile = QosProfile::subscription_default()
        .reliability(match qos.reliability {
            QosReliability::Reliable => Reliability::Reliable {
                when_full: WhenFull::Fail,
            },
            QosReliability::BestEffort => Reliability::BestEffort,
        })
        .durability(match qos.durability {
            QosDurability::Volatile => Durability::Volatile,
            QosDurability::TransientLocal => Durability::TransientLocal,
        });
    match qos.history {
        QosHistory::KeepLast => profile.history(History::KeepLast { depth: qos.depth }),
        QosHistory::KeepAll => profile.history(History::KeepAll),
    }
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
    crate::memory::configure_allocator();
    let Some(names) = parse_command_line(argv)? else {
        return Ok(()); // --help
    };
    let startup = startup_params(&names)?;
    let started = Instant::now();
    let params = startup.params;
    let processor = Processor::new(params.clone(), 0)?;
    let shared = Arc::new(Shared::new(params.clone(), started));

    let domain_id = domain_id_from_env()?;
    let discovery = Discovery::from_env(|name| std::env::var(name).ok())?;
    let context = Context::from_domain_participant(discovery.participant(domain_id)?)
        .map_err(|e| format!("cannot start DDS: {e:?}"))?;
    let mut node = create_node(&context, &shared, &params, &names)?;
    let fq_name = fully_qualified(&names.namespace, &names.node_name);
    RosoutLogger::attach(node.logging_handle(), &names.node_name);
    info!("node {fq_name} on DDS domain {domain_id}");
    // Logged once /rosout is attached, so that ROS tools see them too.
    discovery.log();
    for ignored in &startup.ignored {
        warn!("parameter override ignored: {ignored}");
    }
    if params.use_sim_time {
        // Also in ros2-client's store, so that `ros2 param get` reports it.
        node.set_parameter("use_sim_time", ParameterValue::Boolean(true))?;
        info!("use_sim_time: the node's own stamps follow /clock");
    }
    let clock = subscribe_clock(&mut node, &names)?;
    let image_topic = image_topic_name(&params, &names);
    let receiver = subscribe_image(&mut node, &params, &image_topic)?;
    let publishers = create_publishers(&mut node, &context, &params, &names)?;
    let diagnostics: Publisher<DiagnosticArray> =
        publisher(&mut node, &names.resolve("/diagnostics"), output_qos(10))?;
    info!(
        "waiting for frames ({}) on {image_topic}; publishing on {} and {}",
        if params.compressed_input {
            "sensor_msgs/CompressedImage"
        } else {
            "sensor_msgs/Image"
        },
        names.resolve("~/detections"),
        names.resolve("~/markers")
    );

    let rmw = std::env::var("RMW_IMPLEMENTATION").ok();
    let parameter_services =
        ParameterServices::create(&mut node, &fq_name, mapping_for_rmw(rmw.as_deref()))?;
    spawn_spinner(&mut node)?;
    let node = Arc::new(Mutex::new(node));
    let access = NodeParameters {
        node: Arc::clone(&node),
        shared: Arc::clone(&shared),
    };
    spawn("parameters", move || parameter_services.serve(&access))?;
    spawn_clock_reader(clock, Arc::clone(&shared))?;
    spawn_receiver(receiver, Arc::clone(&shared))?;
    let debug_topic = names.resolve("~/debug_image");
    {
        let shared = Arc::clone(&shared);
        let node = Arc::clone(&node);
        spawn("worker", move || {
            work_loop(processor, publishers, &shared, &node, &names)
        })?;
    }
    // Main thread: diagnostics and debug-image demand.
    let topics = DiagnosticsTopics {
        node_name: fq_name,
        image: image_topic,
        debug_image: debug_topic,
    };
    diagnostics_loop(&node, &shared, &diagnostics, &topics)
}

impl Shared {
    /// The state at start: `params` as generation 0, empty statistics of a node started at
    /// `started`, no frame, no debug-image subscriber, sim time zero.
    fn new(params: NodeParams, started: Instant) -> Shared {
        Shared {
            params: Mutex::new((params, 0)),
            stats: Mutex::new(Stats::new(started)),
            slot: Mutex::new(None),
            slot_filled: Condvar::new(),
            debug_wanted: AtomicBool::new(false),
            sim_time: Mutex::new(Time::default()),
        }
    }
}

/// Parses the command line and starts logging at its level; `None` after printing `--help`.
/// The node's name and namespace (defaults: [`DEFAULT_NODE_NAME`], `/`) and the remappings
/// come back as the [`TopicNames`] every topic is resolved with.
fn parse_command_line(argv: Vec<String>) -> Result<Option<TopicNames>, String> {
    let args = RosArgs::parse(argv).map_err(|e| e.to_string())?;
    if args.other.iter().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}");
        return Ok(None);
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
    Ok(Some(TopicNames {
        args,
        namespace,
        node_name,
    }))
}

/// The validated startup parameters from the parameter files and `-p` assignments; the
/// error says how to pass parameters when no file was given.
fn startup_params(names: &TopicNames) -> Result<StartupParams, String> {
    let args = &names.args;
    let overrides = args
        .parameter_overrides(&names.namespace, &names.node_name)
        .map_err(|e| e.to_string())?;
    NodeParams::from_overrides(&overrides).map_err(|e| {
        if args.params_files.is_empty() {
            format!(
                "{e} (start it with `--ros-args --params-file params/detector.yaml`, or set \
                 parameters with `--ros-args -p name:=value`; see --help)"
            )
        } else {
            e
        }
    })
}

/// The DDS domain from `ROS_DOMAIN_ID` (0 when unset or blank).
fn domain_id_from_env() -> Result<u16, String> {
    match std::env::var("ROS_DOMAIN_ID") {
        Ok(text) if !text.trim().is_empty() => text
            .trim()
            .parse::<u16>()
            .map_err(|_| format!("ROS_DOMAIN_ID `{text}` is not a domain number")),
        _ => Ok(0),
    }
}

/// Creates the ROS 2 node with `/rosout`, its parameters declared with their startup values,
/// and changes validated and applied through `shared` ([`apply_parameter`]).
fn create_node(
    context: &Context,
    shared: &Arc<Shared>,
    params: &NodeParams,
    names: &TopicNames,
) -> Result<Node, String> {
    let mut options = NodeOptions::new()
        .enable_rosout(true)
        // Served by crate::param_services instead, which also speaks Cyclone's mapping.
        .start_parameter_services(false);
    for (name, value) in params.values() {
        options = options.declare_parameter(name, value.clone().into());
    }
    let for_validator = Arc::clone(shared);
    let for_action = Arc::clone(shared);
    options = options
        .parameter_validator(Box::new(move |name, value| {
            let value = value.clone().into();
            lock(&for_validator.params).0.with(name, &value).map(|_| ())
        }))
        .parameter_set_action(Box::new(move |name, value| {
            apply_parameter(&for_action, name, value)
        }));
    context
        .new_node(
            NodeName::new(&names.namespace, &names.node_name).map_err(|e| e.to_string())?,
            options,
        )
        .map_err(|e| format!("cannot create node: {e:?}"))
}

/// The `/clock` subscription (rosgraph_msgs/Clock, read here: ros2-client's own /clock
/// reader expects another type). Kept for the node's life, since
/// `ros2 param set use_sim_time true` may come later.
fn subscribe_clock(node: &mut Node, names: &TopicNames) -> Result<Subscription<Clock>, String> {
    let qos = QosProfile::subscription_default()
        .reliability(Reliability::BestEffort)
        .history(History::KeepLast { depth: 1 });
    let clock_topic = names.resolve("/clock");
    let t = create_topic::<Clock>(node, &clock_topic, &qos)?;
    node.create_subscription(&t, Some(qos))
        .map_err(|e| format!("cannot subscribe to /clock: {e:?}"))
}

/// The resolved image topic: `image`, or `image/compressed` with
/// `image_transport:=compressed` (where image_transport's compressed plugin publishes).
fn image_topic_name(params: &NodeParams, names: &TopicNames) -> String {
    if params.compressed_input {
        format!("{}/compressed", names.resolve("image"))
    } else {
        names.resolve("image")
    }
}

/// Subscribes to `image_topic` with the transport and QoS the parameters name, warning about
/// QoS overrides that name another topic.
fn subscribe_image(
    node: &mut Node,
    params: &NodeParams,
    image_topic: &str,
) -> Result<Receiver, String> {
    let qos = image_qos(params.image_qos(image_topic));
    for unused in params.unused_qos_overrides(image_topic) {
        warn!("parameter override ignored: {unused}: the image topic is {image_topic}");
    }
    Ok(if params.compressed_input {
        let t = create_topic::<CompressedImage>(node, image_topic, &qos)?;
        Receiver::Compressed(
            node.create_subscription(&t, Some(qos))
                .map_err(|e| format!("cannot subscribe to {image_topic}: {e:?}"))?,
        )
    } else {
        let t = create_topic::<Image>(node, image_topic, &qos)?;
        Receiver::Raw(
            node.create_subscription(&t, Some(qos))
                .map_err(|e| format!("cannot subscribe to {image_topic}: {e:?}"))?,
        )
    })
}

/// The output publishers, with those of the configured marker IDs and pairs created now, so
/// that subscribers are matched before the first frame (samples sent before matching are
/// lost).
fn create_publishers(
    node: &mut Node,
    context: &Context,
    params: &NodeParams,
    names: &TopicNames,
) -> Result<Publishers, String> {
    let mut publishers = Publishers {
        markers: publisher(node, &names.resolve("~/markers"), output_qos(10))?,
        detections: publisher(node, &names.resolve("~/detections"), output_qos(10))?,
        tf: publisher(node, &names.resolve("/tf"), output_qos(100))?,
        debug: bounded_publisher(
            node,
            context,
            &names.resolve("~/debug_image"),
            output_qos(1),
            DEBUG_IMAGE_WINDOW,
        )?,
        poses: BTreeMap::new(),
        relative: BTreeMap::new(),
    };
    for id in &params.marker_ids {
        publishers.pose(*id, node, names)?;
    }
    for pair in &params.relative_pairs {
        publishers.relative_pose(*pair, node, names)?;
    }
    Ok(publishers)
}

/// Starts a thread named `name` running `body`.
fn spawn<T: Send + 'static>(
    name: &str,
    body: impl FnOnce() -> T + Send + 'static,
) -> Result<(), String> {
    std::thread::Builder::new()
        .name(name.into())
        .spawn(body)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

/// Starts the thread spinning ros2-client's graph bookkeeping (discovery, `/clock`).
fn spawn_spinner(node: &mut Node) -> Result<(), String> {
    let spinner = node
        .spinner()
        .map_err(|e| format!("cannot start the ROS 2 spinner: {e:?}"))?;
    spawn("spinner", move || {
        if let Err(e) = futures::executor::block_on(spinner.spin()) {
            error!("spinner stopped: {e:?}");
        }
    })
}

/// Starts the thread keeping the latest `/clock` time in `shared`.
fn spawn_clock_reader(clock: Subscription<Clock>, shared: Arc<Shared>) -> Result<(), String> {
    spawn("clock", move || loop {
        match futures::executor::block_on(clock.async_take()) {
            Ok((tick, _)) => *lock(&shared.sim_time) = tick.clock,
            Err(ros2_client::ReadError::Closed) => return,
            Err(e) => warn!("bad /clock message: {e}"),
        }
    })
}

/// Starts the receiver thread ([`receive_loop`]) of the chosen transport.
fn spawn_receiver(receiver: Receiver, shared: Arc<Shared>) -> Result<(), String> {
    spawn("receiver", move || match receiver {
        Receiver::Raw(s) => receive_loop(s, &shared, check_raw),
        Receiver::Compressed(s) => receive_loop(s, &shared, check_compressed),
    })
}

/// The names `/diagnostics` reports with, and the topic whose subscribers it watches.
struct DiagnosticsTopics {
    /// The node's fully qualified name.
    node_name: String,
    /// The resolved image topic.
    image: String,
    /// The resolved `~/debug_image` topic.
    debug_image: String,
}

/// The main thread's loop, once per [`DIAGNOSTICS_PERIOD`]: notes whether anyone subscribes
/// to `~/debug_image` and publishes `/diagnostics`, stamped with the node's clock (`/clock`
/// under `use_sim_time`).
fn diagnostics_loop(
    node: &Mutex<Node>,
    shared: &Shared,
    diagnostics: &Publisher<DiagnosticArray>,
    topics: &DiagnosticsTopics,
) -> ! {
    let mut memory = crate::memory::MemoryRelease::default();
    loop {
        std::thread::sleep(DIAGNOSTICS_PERIOD);
        let wanted = lock(node).subscription_count(&topics.debug_image) > 0;
        shared.debug_wanted.store(wanted, Ordering::Relaxed);
        let stamp = if lock(&shared.params).0.use_sim_time {
            *lock(&shared.sim_time)
        } else {
            Time::now()
        };
        let report =
            lock(&shared.stats).report(Instant::now(), stamp, &topics.node_name, &topics.image);
        if let Err(e) = diagnostics.publish(report) {
            warn!("cannot publish diagnostics: {}", write_failure(&e));
        }
        memory.when_due(Instant::now());
    }
}

/// Validates and applies one parameter change (called by the parameter store, both for the
/// initial values and for `ros2 param set`).
fn apply_parameter(shared: &Shared, name: &str, value: &ParameterValue) -> Result<(), String> {
    let mut guard = lock(&shared.params);
    let updated = guard.0.with(name, &value.clone().into())?;
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
            params = params.with(name, &value.clone().into())?;
        }
        Ok(())
    }
}

/// The process logger: the terminal (env_logger) for everything, and `/rosout`
/// (`rcl_interfaces/Log`) for the node's own warnings and errors once the node exists, as
/// rclcpp's `RCLCPP_WARN` does.
struct RosoutLogger {
    terminal: env_logger::Logger,
}

/// The node's `/rosout` writer and logger name, set once the node is created.
static ROSOUT: OnceLock<(NodeLoggingHandle, String)> = OnceLock::new();

impl RosoutLogger {
    /// Sends the node's warnings and errors to `/rosout` from now on.
    fn attach(handle: NodeLoggingHandle, node_name: &str) {
        // A second node in one process (tests) keeps the first writer.
        ROSOUT.set((handle, node_name.to_string())).unwrap_or(());
    }
}

impl log::Log for RosoutLogger {
    fn enabled(&self, metadata: &log::Metadata) -> bool {
        self.terminal.enabled(metadata)
    }

    fn log(&self, record: &log::Record) {
        if !self.terminal.matches(record) {
            return;
        }
        self.terminal.log(record);
        let ours = record.target().starts_with("vernier_ros") || record.target() == "detector";
        if ours && record.level() <= log::Level::Warn {
            if let Some((handle, name)) = ROSOUT.get() {
                let level = if record.level() == log::Level::Error {
                    ros2_client::log::LogLevel::Error
                } else {
                    ros2_client::log::LogLevel::Warn
                };
                let stamp =
                    ros2_client::builtin_interfaces::Time::try_from(std::time::SystemTime::now())
                        .unwrap_or(ros2_client::builtin_interfaces::Time::ZERO);
                handle.rosout_raw(
                    stamp,
                    level,
                    name,
                    &record.args().to_string(),
                    record.file().unwrap_or_default(),
                    record.module_path().unwrap_or_default(),
                    record.line().unwrap_or(0),
                );
            }
        }
    }

    fn flush(&self) {
        self.terminal.flush();
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
    let terminal = env_logger::Builder::new()
        .filter_level(log::LevelFilter::Warn)
        .filter_module("vernier_ros", filter)
        .filter_module("detector", filter)
        .parse_env("RUST_LOG")
        .build();
    let max_level = terminal.filter();
    // A second initialisation (tests) is harmless.
    if log::set_boxed_logger(Box::new(RosoutLogger { terminal })).is_ok() {
        log::set_max_level(max_level);
    }
}

fn create_topic<T: RosType>(
    node: &Node,
    absolute_name: &str,
    qos: &QosProfile,
) -> Result<ros2_client::dds::rustdds::Topic, String> {
    let name = Name::parse(absolute_name)
        .map_err(|e| format!("invalid topic name {absolute_name}: {e}"))?;
    node.create_topic(&name, MessageTypeName::new(T::PACKAGE, T::NAME), qos)
        .map_err(|e| format!("cannot create topic {absolute_name}: {e:?}"))
}

fn publisher<T: RosType + ros2_client::Message>(
    node: &mut Node,
    absolute_name: &str,
    qos: QosProfile,
) -> Result<Publisher<T>, String> {
    let topic = create_topic::<T>(node, absolute_name, &qos)?;
    node.create_publisher(&topic, Some(qos))
        .map_err(|e| format!("cannot publish on {absolute_name}: {e:?}"))
}

/// A publisher whose writer holds at most `max_samples` unacknowledged samples.
///
/// rustdds's reliable writer keeps up to 8192 samples that a reader has not acknowledged,
/// whatever its `KeepLast` depth: a `~/debug_image` reader slower than the frame rate made
/// the node hold hundreds of megabytes of annotated frames (the soak test,
/// test/run_soak.sh). The topic carries a resource limit of `max_samples`, which the writer
/// inherits (ros2-client's `QosProfile` has none); a write beyond it fails at once
/// (`WhenFull::Fail`), and the frame is skipped.
fn bounded_publisher<T: RosType + ros2_client::Message>(
    node: &mut Node,
    context: &Context,
    absolute_name: &str,
    qos: QosProfile,
    max_samples: i32,
) -> Result<Publisher<T>, String> {
    let name = Name::parse(absolute_name)
        .map_err(|e| format!("invalid topic name {absolute_name}: {e}"))?;
    let limits = QosPolicyBuilder::new()
        .resource_limits(policy::ResourceLimits {
            max_samples,
            max_instances: 1,
            max_samples_per_instance: max_samples,
        })
        .build();
    // Absolute names need no node to expand `~`.
    let anyone = NodeName::new("/", "node").map_err(|e| e.to_string())?;
    let topic = context
        .domain_participant()
        .create_topic(
            name.to_dds_name("rt", &anyone, ""),
            MessageTypeName::new(T::PACKAGE, T::NAME).dds_msg_type(),
            &QosPolicies::from(&qos).modify_by(&limits),
            TopicKind::NoKey,
        )
        .map_err(|e| format!("cannot create topic {absolute_name}: {e:?}"))?;
    node.create_publisher(&topic, Some(qos))
        .map_err(|e| format!("cannot publish on {absolute_name}: {e:?}"))
}

/// The image subscription of the chosen transport.
enum Receiver {
    Raw(Subscription<Image>),
    Compressed(Subscription<CompressedImage>),
}

/// A raw image passes when its size, step and encoding agree (checked before the slot, so a
/// bad message never displaces a good frame).
fn check_raw(image: Image) -> Result<Input, String> {
    crate::processing::check_image(&image).map_err(|bad| bad.0)?;
    Ok(Input::Raw(image))
}

/// A compressed image is decoded on the worker thread; only emptiness is checked here.
fn check_compressed(image: CompressedImage) -> Result<Input, String> {
    if image.data.is_empty() {
        return Err(format!("empty `{}` compressed image", image.format));
    }
    Ok(Input::Compressed(image))
}

/// Takes image samples, rejects bad ones, keeps only the newest good one in the slot.
fn receive_loop<M: ros2_client::Message + 'static>(
    subscription: Subscription<M>,
    shared: &Shared,
    check: fn(M) -> Result<Input, String>,
) {
    let mut bad_warning = Throttle::new(WARN_PERIOD);
    loop {
        let sample = futures::executor::block_on(subscription.async_take());
        let arrived = Instant::now();
        let reason = match sample {
            Ok((message, _info)) => match check(message) {
                Ok(message) => {
                    lock(&shared.stats).record(arrived, Event::Received);
                    let frame = Frame { message, arrived };
                    let replaced = lock(&shared.slot).replace(frame).is_some();
                    if replaced {
                        lock(&shared.stats).record(arrived, Event::Dropped);
                    }
                    shared.slot_filled.notify_one();
                    continue;
                }
                Err(bad) => bad,
            },
            Err(ros2_client::ReadError::Closed) => {
                error!("image subscription closed");
                return;
            }
            Err(e) => format!("undecodable message: {e}"),
        };
        record_bad(shared, arrived, reason.clone());
        if let Some(held_back) = bad_warning.allow(arrived) {
            warn!("bad image message ignored: {reason} ({held_back} more since the last warning)");
        }
    }
}

fn record_bad(shared: &Shared, at: Instant, reason: String) {
    let mut stats = lock(&shared.stats);
    stats.record(at, Event::Bad);
    stats.last_bad_reason = reason;
}

/// Output publishers; per-marker and per-pair ones are created on first use.
struct Publishers {
    markers: Publisher<MarkerPoseArray>,
    detections: Publisher<Detection3DArray>,
    tf: Publisher<TfMessage>,
    debug: Publisher<Image>,
    poses: BTreeMap<u64, MarkerPublishers>,
    relative: BTreeMap<(u64, u64), Publisher<PoseStamped>>,
}

/// `~/marker_<id>/pose` and `~/marker_<id>/pose_with_covariance`.
struct MarkerPublishers {
    pose: Publisher<PoseStamped>,
    with_covariance: Publisher<PoseWithCovarianceStamped>,
}

impl Publishers {
    /// The publishers of marker `id`, created on first use.
    fn pose(
        &mut self,
        id: u64,
        node: &mut Node,
        names: &TopicNames,
    ) -> Result<&MarkerPublishers, String> {
        Ok(match self.poses.entry(id) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => {
                let name = names.resolve(&format!("~/marker_{id}/pose"));
                let pose = publisher(node, &name, output_qos(10))?;
                let name = names.resolve(&format!("~/marker_{id}/pose_with_covariance"));
                let with_covariance = publisher(node, &name, output_qos(10))?;
                e.insert(MarkerPublishers {
                    pose,
                    with_covariance,
                })
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
    processor: Processor,
    publishers: Publishers,
    shared: &Shared,
    node: &Mutex<Node>,
    names: &TopicNames,
) {
    let mut worker = Worker {
        processor,
        publishers,
        not_found_warning: Throttle::new(WARN_PERIOD),
        publish_warning: Throttle::new(WARN_PERIOD),
        frame_warning: Throttle::new(WARN_PERIOD),
        last_start: None,
        last_debug: None,
    };
    loop {
        let frame = take_frame(shared);
        worker.handle(&frame, shared, node, names);
    }
}

/// Waits for a frame in the slot and takes it.
fn take_frame(shared: &Shared) -> Frame {
    let mut slot = lock(&shared.slot);
    loop {
        if let Some(frame) = slot.take() {
            return frame;
        }
        slot = shared
            .slot_filled
            .wait(slot)
            .unwrap_or_else(|poisoned| poisoned.into_inner());
    }
}

/// The worker thread's state between frames.
struct Worker {
    processor: Processor,
    publishers: Publishers,
    /// Bad images and frames without a marker.
    not_found_warning: Throttle,
    publish_warning: Throttle,
    /// Frames published in the default camera frame.
    frame_warning: Throttle,
    /// When the last frame not skipped by `max_rate` was taken.
    last_start: Option<Instant>,
    /// When the last `~/debug_image` was published.
    last_debug: Option<Instant>,
}

impl Worker {
    /// Processes one frame and publishes its outputs (unless `max_rate` skips it), recording
    /// it in the statistics.
    fn handle(&mut self, frame: &Frame, shared: &Shared, node: &Mutex<Node>, names: &TopicNames) {
        let start = Instant::now();
        self.follow_parameters(shared);
        if self.rate_limited(start) {
            lock(&shared.stats).record(start, Event::RateLimited);
            return;
        }
        self.last_start = Some(start);
        let processed = match &frame.message {
            Input::Raw(image) => self.processor.process(image),
            Input::Compressed(image) => self.processor.process_compressed(image),
        };
        let output = match processed {
            Ok(done) => done,
            Err(bad) => {
                // A compressed image that does not decode, or one above max_image_pixels.
                if let Some(held_back) = self.not_found_warning.allow(start) {
                    warn!("bad image ignored: {bad} ({held_back} more since the last warning)");
                }
                record_bad(shared, start, bad.0);
                return;
            }
        };
        self.warn_about(&output, start);
        let params = self.processor.params();
        let mut failures = publish(&output, &mut self.publishers, node, names, params);
        if let Some(failure) = self.publish_debug_image(shared, &output, start) {
            failures.push(failure);
        }
        record_processed(shared, start, frame.arrived, output.detect_error.is_some());
        if let Some(first) = failures.first() {
            if let Some(held_back) = self.publish_warning.allow(start) {
                warn!("publishing failed: {first} ({held_back} more since the last warning)");
            }
        }
    }

    /// Rebuilds the detector when the parameters changed since it was built.
    fn follow_parameters(&mut self, shared: &Shared) {
        let guard = lock(&shared.params);
        if guard.1 != self.processor.generation() {
            if let Err(e) = self.processor.update(guard.0.clone(), guard.1) {
                // Validated before acceptance; only a vanished pattern file gets here.
                warn!("keeping the previous detector: {e}");
            }
        }
    }

    /// Whether a frame taken at `start` comes sooner than `max_rate` (Hz; 0: no limit)
    /// allows after the last one processed.
    fn rate_limited(&self, start: Instant) -> bool {
        let max_rate = self.processor.params().max_rate;
        max_rate > 0.0
            && self
                .last_start
                .is_some_and(|last| start.duration_since(last).as_secs_f64() < 1.0 / max_rate)
    }

    /// The throttled warnings about a processed frame: published in the default camera
    /// frame, no marker found.
    fn warn_about(&mut self, output: &FrameOutput, start: Instant) {
        if output.frame_defaulted {
            if let Some(held_back) = self.frame_warning.allow(start) {
                warn!(
                    "the image has an empty header.frame_id and camera_frame is not set: \
                     publishing in frame `{DEFAULT_CAMERA_FRAME}` ({held_back} more since the \
                     last warning)"
                );
            }
        }
        if let Some(reason) = &output.detect_error {
            if let Some(held_back) = self.not_found_warning.allow(start) {
                warn!("no marker found: {reason} ({held_back} more since the last warning)");
            }
        }
    }

    /// Publishes the annotated frame on `~/debug_image` while someone subscribes, at most
    /// once per [`DEBUG_IMAGE_PERIOD`] (it costs a copy of the frame); returns the failure.
    fn publish_debug_image(
        &mut self,
        shared: &Shared,
        output: &FrameOutput,
        start: Instant,
    ) -> Option<String> {
        if !shared.debug_wanted.load(Ordering::Relaxed)
            || self
                .last_debug
                .is_some_and(|t| start.duration_since(t) < DEBUG_IMAGE_PERIOD)
        {
            return None;
        }
        let grey = self.processor.last_frame()?;
        self.last_debug = Some(start);
        let debug = annotate(grey, &output.raw, &output.markers.header);
        let published = self.publishers.debug.publish(debug);
        published
            .err()
            .map(|e| format!("debug image: {}", write_failure(&e)))
    }
}

/// Records a processed frame taken at `start` that arrived at `arrived` (processing time
/// and latency, ms), and whether it held no marker.
fn record_processed(shared: &Shared, start: Instant, arrived: Instant, not_found: bool) {
    let now = Instant::now();
    let mut stats = lock(&shared.stats);
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    stats.record(
        now,
        Event::Processed {
            processing_ms: ms(now.duration_since(start)),
            latency_ms: ms(now.duration_since(arrived)),
        },
    );
    if not_found {
        stats.record(now, Event::NotFound);
    }
}

/// Whether marker `id` gets (or has) its own pose publishers, given the IDs that have them:
/// listed IDs always, others until `max_marker_publishers` of them exist (each is kept once
/// created: a new DDS writer loses its first samples to discovery).
fn may_publish<T>(id: u64, with_publishers: &BTreeMap<u64, T>, params: &NodeParams) -> bool {
    let unlisted = || {
        with_publishers
            .keys()
            .filter(|i| !params.marker_ids.contains(i))
            .count()
    };
    with_publishers.contains_key(&id)
        || params.marker_ids.contains(&id)
        || unlisted() < params.max_marker_publishers
}

/// What a failed write says, without the message it carries: the error's `{:?}` prints the
/// whole message, megabytes of text for a `~/debug_image` frame, once per frame while a slow
/// reader keeps the writer full (found by the soak test, test/run_soak.sh).
fn write_failure<D>(e: &ros2_client::WriteError<D>) -> String {
    e.to_string()
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
    // Per-marker poses before the arrays: a controller reading an array sees them all sent.
    for ((id, pose), (_, with_covariance)) in output.poses.iter().zip(&output.poses_with_covariance)
    {
        if !may_publish(*id, &publishers.poses, params) {
            failures.push(format!(
                "marker {id}: max_marker_publishers ({}) reached, its pose is only in \
                 ~/markers and ~/detections",
                params.max_marker_publishers
            ));
            continue;
        }
        let result = match publishers.poses.get(id) {
            Some(p) => Ok(p),
            None => publishers.pose(*id, &mut lock(node), names),
        }
        .and_then(|p| {
            p.pose
                .publish(pose.clone())
                .map_err(|e| write_failure(&e))?;
            p.with_covariance
                .publish(with_covariance.clone())
                .map_err(|e| write_failure(&e))
        });
        if let Err(e) = result {
            failures.push(format!("marker {id} pose: {e}"));
        }
    }
    for (pair, pose) in &output.relative {
        let result = match publishers.relative.get(pair) {
            Some(p) => p.publish(pose.clone()).map_err(|e| write_failure(&e)),
            None => publishers
                .relative_pose(*pair, &mut lock(node), names)
                .and_then(|p| p.publish(pose.clone()).map_err(|e| write_failure(&e))),
        };
        if let Err(e) = result {
            failures.push(format!("relative pose {}:{}: {e}", pair.0, pair.1));
        }
    }
    if params.publish_tf && !output.tf.transforms.is_empty() {
        if let Err(e) = publishers.tf.publish(output.tf.clone()) {
            failures.push(format!("/tf: {}", write_failure(&e)));
        }
    }
    if let Err(e) = publishers.detections.publish(output.detections.clone()) {
        failures.push(format!("detections: {}", write_failure(&e)));
    }
    if let Err(e) = publishers.markers.publish(output.markers.clone()) {
        failures.push(format!("markers: {}", write_failure(&e)));
    }
    failures
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::ParamValue;

    #[test]
    fn a_failed_write_is_described_without_its_message() {
        let frame = Image {
            width: 1024,
            height: 1024,
            step: 3 * 1024,
            encoding: "rgb8".into(),
            data: vec![255; 3 * 1024 * 1024],
            ..Image::default()
        };
        let text = write_failure(&ros2_client::WriteError::WouldBlock { data: frame });
        assert!(text.len() < 100, "{} bytes: {}", text.len(), &text[..100]);
    }

    #[test]
    fn per_marker_publishers_are_bounded_for_unlisted_ids() {
        let startup = NodeParams::from_overrides(&[
            ("period".into(), ParamValue::Double(10.0)),
            ("marker_ids".into(), ParamValue::IntegerArray(vec![5])),
            ("max_marker_publishers".into(), ParamValue::Integer(2)),
        ]);
        let params = startup.map(|s| s.params).unwrap_or_else(|e| panic!("{e}"));
        let with = |ids: &[u64]| -> BTreeMap<u64, ()> { ids.iter().map(|&i| (i, ())).collect() };
        // Listed IDs always; two unlisted ones; then only those that already have theirs.
        assert!(may_publish(5, &with(&[]), &params));
        assert!(may_publish(7, &with(&[5]), &params));
        assert!(may_publish(8, &with(&[5, 7]), &params));
        assert!(!may_publish(9, &with(&[5, 7, 8]), &params));
        assert!(may_publish(7, &with(&[5, 7, 8]), &params));
        assert!(may_publish(5, &with(&[5, 7, 8]), &params));
    }
}
