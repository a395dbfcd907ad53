//! The node's parameters: declaration (name, type, default, description), validation of
//! every value with a reason, and the mapping onto [`vernier::detector::DetectorSettings`].
//!
//! [`NodeParams`] is the typed, validated set. A change arrives as `(name, value)`;
//! [`NodeParams::with`] returns the new set or the reason it is rejected, so the same code
//! serves the command line, parameter files and the `ros2 param set` services.

use std::collections::BTreeMap;
use std::path::PathBuf;
use vernier::detector::{DetectorConfig, DetectorSettings, MarkerKind};
use vernier::{limits, Detector};

/// A ROS 2 parameter value (the variants of `rcl_interfaces/ParamValue`). With the
/// `ros2-client` feature it converts both ways to `ros2_client::ParameterValue`.
#[derive(Clone, Debug, PartialEq)]
pub enum ParamValue {
    /// No value.
    NotSet,
    /// `bool`.
    Boolean(bool),
    /// `int64`.
    Integer(i64),
    /// `float64`.
    Double(f64),
    /// `string`.
    String(String),
    /// `byte[]`.
    ByteArray(Vec<u8>),
    /// `bool[]`.
    BooleanArray(Vec<bool>),
    /// `int64[]`.
    IntegerArray(Vec<i64>),
    /// `float64[]`.
    DoubleArray(Vec<f64>),
    /// `string[]`.
    StringArray(Vec<String>),
}

impl ParamValue {
    /// The type's name as `ros2 param describe` prints it.
    pub fn type_name(&self) -> &'static str {
        match self {
            ParamValue::NotSet => "not set",
            ParamValue::Boolean(_) => "boolean",
            ParamValue::Integer(_) => "integer",
            ParamValue::Double(_) => "double",
            ParamValue::String(_) => "string",
            ParamValue::ByteArray(_) => "byte array",
            ParamValue::BooleanArray(_) => "boolean array",
            ParamValue::IntegerArray(_) => "integer array",
            ParamValue::DoubleArray(_) => "double array",
            ParamValue::StringArray(_) => "string array",
        }
    }
}

#[cfg(feature = "ros2-client")]
mod ros2_client_values {
    use super::ParamValue;
    use ros2_client::ParameterValue as V;

    impl From<ParamValue> for V {
        fn from(v: ParamValue) -> V {
            match v {
                ParamValue::NotSet => V::NotSet,
                ParamValue::Boolean(b) => V::Boolean(b),
                ParamValue::Integer(i) => V::Integer(i),
                ParamValue::Double(d) => V::Double(d),
                ParamValue::String(s) => V::String(s),
                ParamValue::ByteArray(a) => V::ByteArray(a),
                ParamValue::BooleanArray(a) => V::BooleanArray(a),
                ParamValue::IntegerArray(a) => V::IntegerArray(a),
                ParamValue::DoubleArray(a) => V::DoubleArray(a),
                ParamValue::StringArray(a) => V::StringArray(a),
            }
        }
    }

    impl From<V> for ParamValue {
        fn from(v: V) -> ParamValue {
            match v {
                V::NotSet => ParamValue::NotSet,
                V::Boolean(b) => ParamValue::Boolean(b),
                V::Integer(i) => ParamValue::Integer(i),
                V::Double(d) => ParamValue::Double(d),
                V::String(s) => ParamValue::String(s),
                V::ByteArray(a) => ParamValue::ByteArray(a),
                V::BooleanArray(a) => ParamValue::BooleanArray(a),
                V::IntegerArray(a) => ParamValue::IntegerArray(a),
                V::DoubleArray(a) => ParamValue::DoubleArray(a),
                V::StringArray(a) => ParamValue::StringArray(a),
            }
        }
    }
}

/// The inclusive range of a numeric parameter (besides 0 where 0 means "default").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamRange {
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
    /// 0 is accepted too and means "default" (or "none").
    pub zero_means_default: bool,
}

/// One declared parameter: the single source of its name, type, default, unit, range and
/// documentation (the node declares it, `ros2 param describe` reports it, `vernier bag` reads
/// it, and params/detector.yaml is generated from it: [`parameter_file_yaml`]).
#[derive(Clone, Debug)]
pub struct ParamSpec {
    /// Parameter name.
    pub name: &'static str,
    /// Default value (its variant is the parameter's type).
    pub default: ParamValue,
    /// Unit of a numeric value (`px`, `Hz`, ...); empty when it has none.
    pub unit: &'static str,
    /// Accepted range of a numeric value, when bounded.
    pub range: Option<ParamRange>,
    /// What it does.
    pub description: &'static str,
    /// Value written in the shipped params/detector.yaml when it differs from the default (an
    /// example the user edits); `None` = the default, or commented out for an empty list.
    pub file_value: Option<ParamValue>,
    /// Only read at start-up (`ros2 param set` refuses it).
    pub read_only: bool,
}

/// Image subscription reliability (`qos_overrides.<topic>.subscription.reliability`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QosReliability {
    /// Every sample is delivered (the publisher must offer reliable too).
    Reliable,
    /// Samples may be lost; matches every publisher (camera drivers' default).
    BestEffort,
}

/// Image subscription history.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QosHistory {
    /// Keep the newest `depth` samples.
    KeepLast,
    /// Keep every sample (bounded by the middleware's resource limits).
    KeepAll,
}

/// Image subscription durability.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QosDurability {
    /// Only samples published after the subscription matched.
    Volatile,
    /// Also the publisher's last samples from before.
    TransientLocal,
}

/// Quality of service of the image subscription, DDS-free: from `image_qos` and then
/// `qos_overrides.<image topic>.subscription.*` (rclcpp's syntax).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageQos {
    /// Reliability.
    pub reliability: QosReliability,
    /// History.
    pub history: QosHistory,
    /// Queue depth with [`QosHistory::KeepLast`], samples.
    pub depth: usize,
    /// Durability.
    pub durability: QosDurability,
}

impl ImageQos {
    /// rclcpp's `SensorDataQoS`: best effort, volatile, keep last 5.
    pub const SENSOR_DATA: ImageQos = ImageQos {
        reliability: QosReliability::BestEffort,
        history: QosHistory::KeepLast,
        depth: 5,
        durability: QosDurability::Volatile,
    };
    /// rclcpp's default: reliable, volatile, keep last 10.
    pub const RELIABLE: ImageQos = ImageQos {
        reliability: QosReliability::Reliable,
        history: QosHistory::KeepLast,
        depth: 10,
        durability: QosDurability::Volatile,
    };

    /// Applies one `qos_overrides` policy (`reliability`, `history`, `depth`, `durability`).
    fn set(&mut self, policy: &str, value: &ParamValue) -> Result<(), String> {
        let text = match value {
            ParamValue::String(s) => Some(s.as_str()),
            _ => None,
        };
        match (policy, text, value) {
            ("reliability", Some("reliable"), _) => self.reliability = QosReliability::Reliable,
            ("reliability", Some("best_effort"), _) => {
                self.reliability = QosReliability::BestEffort
            }
            ("history", Some("keep_last"), _) => self.history = QosHistory::KeepLast,
            ("history", Some("keep_all"), _) => self.history = QosHistory::KeepAll,
            ("durability", Some("volatile"), _) => self.durability = QosDurability::Volatile,
            ("durability", Some("transient_local"), _) => {
                self.durability = QosDurability::TransientLocal
            }
            ("depth", _, ParamValue::Integer(d)) if (1..=10_000).contains(d) => {
                self.depth = *d as usize
            }
            ("reliability", ..) => return Err("must be reliable or best_effort".into()),
            ("history", ..) => return Err("must be keep_last or keep_all".into()),
            ("durability", ..) => return Err("must be volatile or transient_local".into()),
            ("depth", ..) => return Err("must be an integer in 1..=10000".into()),
            _ => {
                return Err(
                    "unknown policy (reliability, history, depth and durability can be set)".into(),
                )
            }
        }
        Ok(())
    }
}

/// Parameters that the ROS client library declares on every node; the node passes them on.
pub const CLIENT_LIBRARY_PARAMETERS: &[&str] = &["use_sim_time"];

/// Prefix of rclcpp's QoS override parameters.
pub const QOS_OVERRIDES_PREFIX: &str = "qos_overrides.";

/// Smallest calibrated `pixel_size` the node takes, metres per pixel (1 pm: far below any
/// optical microscope's).
const MIN_PIXEL_SIZE_M: f64 = 1e-12;
/// Largest `focal_length_px` the node takes, pixels (a 10⁷-pixel focal length is
/// orthographic for any sensor).
const MAX_FOCAL_LENGTH_PX: f64 = 1e7;
/// Largest calibrated `pixel_size` the node takes, metres per pixel (10 cm).
const MAX_PIXEL_SIZE_M: f64 = 0.1;

/// Every parameter of the node, in documentation order (params/detector.yaml follows it).
/// Kept whole and long: it is one declarative table, read top to bottom as the reference.
pub fn specs() -> Vec<ParamSpec> {
    use ParamValue as V;
    let spec = |name, default, description| ParamSpec {
        name,
        default,
        unit: "",
        range: None,
        description,
        file_value: None,
        read_only: false,
    };
    let range = |min: f64, max: f64, zero_means_default| {
        Some(ParamRange {
            min,
            max,
            zero_means_default,
        })
    };
    vec![
        spec(
            "pattern_type",
            V::String("periodic".into()),
            "Marker family: periodic, hpcode, stamp or megarena. A pattern file's class \
             (PeriodicPattern, HPCodePattern, ...) takes precedence.",
        ),
        spec(
            "pattern_file",
            V::String(String::new()),
            "JSON pattern file describing the marker layout; empty = none (then `period` is \
             needed).",
        ),
        ParamSpec {
            range: range(limits::MIN_PERIOD, limits::MAX_PERIOD, true),
            file_value: Some(V::Double(10.0)),
            ..spec(
                "period",
                V::Double(0.0),
                "Physical period of the dot grid, in `period_unit`; 0 = take it from the \
                 pattern file. Set it to your marker's period.",
            )
        },
        spec(
            "period_unit",
            V::String("um".into()),
            "Length unit of `period` and of the pattern file: nm, um, mm or m. Poses are \
             converted to metres with it.",
        ),
        ParamSpec {
            unit: "half periods",
            range: range(
                limits::MIN_CODE_SIZE as f64,
                limits::MAX_CODE_SIZE as f64,
                true,
            ),
            ..spec(
                "code_size",
                V::Integer(0),
                "HP code width in half-period cells, ≡ 1 (mod 4): 33, 37, ...; 0 = pattern \
                 file or default.",
            )
        },
        ParamSpec {
            unit: "bits",
            range: range(
                limits::MIN_CODE_DEPTH as f64,
                limits::MAX_CODE_DEPTH as f64,
                true,
            ),
            ..spec(
                "code_depth",
                V::Integer(0),
                "Megarena LFSR bit depth; 0 = pattern file or default.",
            )
        },
        ParamSpec {
            unit: "px",
            range: range(
                limits::MIN_WINDOW_SIZE as f64,
                limits::MAX_WINDOW_SIZE as f64,
                true,
            ),
            ..spec(
                "window_size",
                V::Integer(0),
                "Side of the square window analysed around each marker (HP code, stamp); \
                 0 = automatic (inside each marker).",
            )
        },
        spec(
            "polarity",
            V::String("auto".into()),
            "Dot polarity: auto (found per marker for HP codes and stamps; bright for periodic \
             and Megarena), bright (bright dots on a dark background) or dark (dark dots on \
             bright).",
        ),
        spec(
            "bitmaps",
            V::StringArray(Vec::new()),
            "Stamp bitmap PNG files (1 = dot), in ID order (pattern_type stamp); e.g. \
             [marker_0.png, marker_1.png].",
        ),
        ParamSpec {
            file_value: Some(V::IntegerArray(vec![0])),
            ..spec(
                "marker_ids",
                V::IntegerArray(Vec::new()),
                "Marker IDs to publish; empty = every marker found. Listed IDs get their \
                 publishers at start-up (no sample lost to discovery).",
            )
        },
        spec(
            "relative_pairs",
            V::StringArray(Vec::new()),
            "Relative poses to publish: \"a:b\" = pose of marker b in marker a's frame, on \
             ~/relative/marker_<a>_<b>/pose (force-sensing flexures); e.g. [\"0:1\", \"0:2\"].",
        ),
        ParamSpec {
            range: range(0.0, 1.0, false),
            ..spec(
                "min_quality",
                V::Double(0.0),
                "Markers whose quality (fraction of the image variance explained by the grid, \
                 [0, 1]) is below this are ignored.",
            )
        },
        spec(
            "camera_frame",
            V::String(String::new()),
            "frame_id of the output poses and parent frame of the TF transforms; empty = the \
             image's header.frame_id, or `camera` (with a warning) when that is empty too.",
        ),
        spec(
            "marker_frame_prefix",
            V::String("vernier_marker_".into()),
            "TF child frame of marker <id>: <marker_frame_prefix><id>.",
        ),
        spec(
            "publish_tf",
            V::Boolean(true),
            "Broadcast camera → marker transforms on /tf.",
        ),
        ParamSpec {
            unit: "Hz",
            range: range(0.0, limits::MAX_RATE, false),
            ..spec(
                "max_rate",
                V::Double(0.0),
                "Highest processing rate: frames arriving sooner than 1/max_rate after the \
                 last processed one are skipped (counted in /diagnostics); 0 = no limit.",
            )
        },
        ParamSpec {
            unit: "px",
            range: range(1.0, i64::MAX as f64, false),
            ..spec(
                "max_image_pixels",
                V::Integer(limits::DEFAULT_MAX_PIXELS as i64),
                "Largest image processed (width × height); larger frames are rejected as bad \
                 images (counted in /diagnostics) before any conversion.",
            )
        },
        spec(
            "pose_3d",
            V::Boolean(false),
            "Also measure the out-of-plane angles (pitch, roll) from the phase planes, with \
             their covariance, for every marker type (HP codes and stamps from their whole-field \
             fit; docs/design.md#pose-3d-markers). The mirror solution is chosen by the \
             perspective cue (pose_3d_cue_strength); a marker with no 3-D solution is published \
             planar and the reason logged.",
        ),
        ParamSpec {
            unit: "px",
            range: range(1.0, MAX_FOCAL_LENGTH_PX, true),
            ..spec(
                "focal_length_px",
                V::Double(0.0),
                "Focal length of a perspective camera, pixels (fx of its calibration, principal \
                 point at the image centre), used with pose_3d: each marker's depth z is \
                 published with its variance, and the angles of markers off the optical axis \
                 are solved in perspective. 0 = orthographic optics (a microscope): z \
                 unobserved.",
            )
        },
        spec(
            "field_fit",
            V::Boolean(true),
            "HP codes and stamps: after decoding, refine each marker on its whole dot field with \
             robust weights (dust, hair and scratches ignored; docs/design.md#field-fit). false \
             keeps the analysis window's planes: faster, less precise. Periodic grids keep the \
             engine's planes either way (their whole-image fit, `vernier detect --field-fit`, \
             costs ~100x the engine).",
        ),
        ParamSpec {
            unit: "m/px",
            range: range(MIN_PIXEL_SIZE_M, MAX_PIXEL_SIZE_M, true),
            ..spec(
                "pixel_size",
                V::Double(0.0),
                "Calibrated object-side pixel size, metres per pixel (measure it with `vernier \
                 calibrate`); 0 = each marker's own measured scale. When set, positions use it \
                 (a 1e-5 scale error costs 5e-3 px at 500 px from the image centre); the \
                 measured scale is still published (measured_pixel_size).",
            )
        },
        spec(
            "tracking",
            V::Boolean(true),
            "Track markers from frame to frame (HP codes and framed stamps): the search runs \
             on the first frame, when a marker is lost or its ID changes, and every \
             reacquire_every frames; in between each marker is measured again from its \
             predicted position, its whole-field fit started from the last frame's. The \
             poses of full detection to a small fraction of their sigma while markers move \
             less than half a period per frame beyond the prediction; new markers appear at \
             the next search.",
        ),
        ParamSpec {
            unit: "frames",
            range: range(0.0, 1e6, false),
            ..spec(
                "reacquire_every",
                V::Integer(30),
                "With tracking, run the full search every this many frames (new markers are \
                 found then); 0 = only when a marker is lost.",
            )
        },
        ParamSpec {
            read_only: true,
            ..spec(
                "image_transport",
                V::String("raw".into()),
                "Input transport: raw (sensor_msgs/Image on `image`) or compressed \
                 (sensor_msgs/CompressedImage, PNG or JPEG, on `image/compressed`, as \
                 image_transport publishes it). Read at start-up.",
            )
        },
        ParamSpec {
            read_only: true,
            ..spec(
                "image_qos",
                V::String("sensor_data".into()),
                "Image subscription QoS: sensor_data (best effort, keep last 5: matches every \
                 camera driver) or reliable (keep last 10). \
                 qos_overrides./<topic>.subscription.reliability|history|depth|durability \
                 override it, as in rclcpp. Read at start-up.",
            )
        },
        ParamSpec {
            range: range(1.0, 100_000.0, false),
            ..spec(
                "max_marker_publishers",
                V::Integer(64),
                "Most per-marker publishers kept for IDs not listed in marker_ids (each is \
                 created on first sight and kept); markers beyond are still in ~/markers and \
                 ~/detections.",
            )
        },
    ]
}

/// Length units accepted by `period_unit`, with their size in metres.
const UNITS: &[(&str, f64)] = &[
    ("nm", 1e-9),
    ("um", 1e-6),
    ("µm", 1e-6),
    ("micrometer", 1e-6),
    ("mm", 1e-3),
    ("m", 1.0),
];

/// Validated node parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeParams {
    /// Raw values by name (all declared parameters, each of its declared type).
    values: BTreeMap<String, ParamValue>,
    /// Detector settings derived from the values.
    pub settings: DetectorSettings,
    /// Metres per pattern unit (`period_unit`).
    pub metres_per_unit: f64,
    /// IDs to publish; empty = all.
    pub marker_ids: Vec<u64>,
    /// `(a, b)`: publish the pose of `b` in `a`'s frame.
    pub relative_pairs: Vec<(u64, u64)>,
    /// Minimum marker quality, `[0, 1]`.
    pub min_quality: f64,
    /// Output frame override (empty = image frame).
    pub camera_frame: String,
    /// TF child frame prefix.
    pub marker_frame_prefix: String,
    /// Broadcast TF.
    pub publish_tf: bool,
    /// Processing rate cap, Hz (0 = none).
    pub max_rate: f64,
    /// Largest image processed, pixels.
    pub max_image_pixels: u64,
    /// Subscribe to `sensor_msgs/CompressedImage` on `<image>/compressed` instead of raw.
    pub compressed_input: bool,
    /// Most publishers kept for IDs not listed in `marker_ids`.
    pub max_marker_publishers: usize,
    /// `tracking`: `Some(reacquire_every)` tracks markers from frame to frame
    /// ([`vernier::Detector::detect_next`]); `None` searches every frame.
    pub tracking: Option<usize>,
    /// `use_sim_time`: the node's own stamps (diagnostics) follow `/clock`.
    pub use_sim_time: bool,
    /// `qos_overrides.<topic>.subscription.<policy>` values given at start-up, validated.
    qos_overrides: Vec<(String, String, ParamValue)>,
}

/// The start-up parameters: the validated set, and the names that were ignored (each with
/// the reason, for a warning), as rclcpp ignores overrides of undeclared parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct StartupParams {
    /// The validated parameters.
    pub params: NodeParams,
    /// `name: reason` of every override that was ignored.
    pub ignored: Vec<String>,
}

impl NodeParams {
    /// The defaults with start-up `overrides` applied in order (later wins): from parameter
    /// files and `-p`. The node's own parameters are validated strictly (errors name the
    /// parameter); `use_sim_time` and `qos_overrides.*` are taken; any other name is ignored
    /// and listed in [`StartupParams::ignored`].
    pub fn from_overrides(overrides: &[(String, ParamValue)]) -> Result<StartupParams, String> {
        let mut values: BTreeMap<String, ParamValue> = specs()
            .into_iter()
            .map(|s| (s.name.to_string(), s.default))
            .collect();
        let mut ignored = Vec::new();
        let mut use_sim_time = false;
        let mut qos_overrides = Vec::new();
        for (name, value) in overrides {
            if let Some(declared) = values.get(name) {
                let value = coerce(name, declared, value)?;
                values.insert(name.clone(), value);
            } else if name == "use_sim_time" {
                use_sim_time = boolean(name, value)?;
            } else if let Some(rest) = name.strip_prefix(QOS_OVERRIDES_PREFIX) {
                match rest.rsplit_once(".subscription.") {
                    Some((topic, policy)) if topic.starts_with('/') => {
                        // Checked now; applied to the image topic once it is resolved.
                        let mut check = ImageQos::SENSOR_DATA;
                        check
                            .set(policy, value)
                            .map_err(|e| format!("`{name}` {e}"))?;
                        qos_overrides.push((topic.to_string(), policy.to_string(), value.clone()));
                    }
                    _ => ignored.push(format!(
                        "{name}: only the image subscription's QoS can be overridden \
                         (qos_overrides./<topic>.subscription.<policy>)"
                    )),
                }
            } else {
                ignored.push(format!("{name}: not a parameter of this node"));
            }
        }
        let mut params = Self::from_values(values)?;
        params.use_sim_time = use_sim_time;
        params.qos_overrides = qos_overrides;
        Ok(StartupParams { params, ignored })
    }

    /// The values to declare on the ROS node, by name.
    pub fn values(&self) -> &BTreeMap<String, ParamValue> {
        &self.values
    }

    /// The parameter set with `name` changed to `value` at run time (`ros2 param set`), or
    /// why the change is rejected: unknown and read-only names are, as in rclcpp.
    pub fn with(&self, name: &str, value: &ParamValue) -> Result<NodeParams, String> {
        if name == "use_sim_time" {
            let mut out = self.clone();
            out.use_sim_time = boolean(name, value)?;
            return Ok(out);
        }
        let declared = self
            .values
            .get(name)
            .ok_or_else(|| format!("unknown parameter `{name}`"))?;
        let value = coerce(name, declared, value)?;
        if specs().iter().any(|s| s.name == name && s.read_only) && &value != declared {
            return Err(format!(
                "`{name}` is read-only: it is read at start-up (set it with --ros-args -p)"
            ));
        }
        let mut values = self.values.clone();
        values.insert(name.to_string(), value);
        let mut out = Self::from_values(values)?;
        out.use_sim_time = self.use_sim_time;
        out.qos_overrides.clone_from(&self.qos_overrides);
        Ok(out)
    }

    /// The image subscription's QoS for the resolved topic `topic`: `image_qos`, then the
    /// `qos_overrides` given for that topic.
    pub fn image_qos(&self, topic: &str) -> ImageQos {
        let mut qos = match self.values.get("image_qos") {
            Some(ParamValue::String(s)) if s == "reliable" => ImageQos::RELIABLE,
            _ => ImageQos::SENSOR_DATA,
        };
        for (t, policy, value) in &self.qos_overrides {
            if t == topic {
                // Validated in from_overrides.
                qos.set(policy, value).unwrap_or(());
            }
        }
        qos
    }

    /// `qos_overrides` entries whose topic is not `topic` (the node warns about them).
    pub fn unused_qos_overrides(&self, topic: &str) -> Vec<String> {
        self.qos_overrides
            .iter()
            .filter(|(t, _, _)| t != topic)
            .map(|(t, policy, _)| format!("{QOS_OVERRIDES_PREFIX}{t}.subscription.{policy}"))
            .collect()
    }

    /// Builds the detector configuration (reads the pattern file).
    pub fn detector_config(&self) -> Result<DetectorConfig, String> {
        self.settings.to_config().map_err(|e| e.to_string())
    }

    /// Builds a detector for these settings.
    pub fn build_detector(&self) -> Result<(Detector, DetectorConfig), String> {
        let config = self.detector_config()?;
        let detector = Detector::new(config.clone())
            .map_err(|e| e.to_string())?
            .with_pixel_size(self.settings.pixel_size);
        Ok((detector, config))
    }

    /// Whether marker `id` is published.
    pub fn tracks(&self, id: u64) -> bool {
        self.marker_ids.is_empty() || self.marker_ids.contains(&id)
    }

    /// Validates every value and derives the typed set, checking the parameters in
    /// declaration order so that the first invalid one is the one reported.
    fn from_values(values: BTreeMap<String, ParamValue>) -> Result<NodeParams, String> {
        let read = ValueReader { values: &values };
        let pattern = PatternValues::read(&read)?;
        let publication = PublicationValues::read(&read)?;
        let pixel_size = match read.double("pixel_size")? {
            0.0 => None,
            v if (MIN_PIXEL_SIZE_M..=MAX_PIXEL_SIZE_M).contains(&v) => {
                Some(v / pattern.metres_per_unit)
            }
            v => {
                return Err(format!(
                    "`pixel_size` must be 0 (measured) or in {MIN_PIXEL_SIZE_M:e}..={MAX_PIXEL_SIZE_M:e} m/px, got {v}"
                ))
            }
        };
        let tracking = read.flag("tracking")?;
        let reacquire_every = read.ranged("reacquire_every")?.unwrap_or(0) as usize;
        let max_image_pixels = u64::try_from(read.integer("max_image_pixels")?)
            .map_err(|_| "`max_image_pixels` must be ≥ 1 pixel".to_string())
            .and_then(|v| limits::check_max_pixels(v).map_err(|e| e.to_string()))?;
        let settings = pattern.settings(&read, pixel_size)?;
        let metres_per_unit = pattern.metres_per_unit;
        let params = NodeParams {
            values,
            settings,
            metres_per_unit,
            marker_ids: publication.marker_ids,
            relative_pairs: publication.relative_pairs,
            min_quality: publication.min_quality,
            camera_frame: publication.camera_frame,
            marker_frame_prefix: publication.marker_frame_prefix,
            publish_tf: publication.publish_tf,
            max_rate: publication.max_rate,
            max_image_pixels,
            compressed_input: publication.compressed_input,
            max_marker_publishers: publication.max_marker_publishers,
            tracking: if tracking {
                Some(reacquire_every)
            } else {
                None
            },
            use_sim_time: false,
            qos_overrides: Vec::new(),
        };
        // The whole configuration must make a detector (period given, pattern file readable,
        // marker type implemented...).
        params.build_detector()?;
        Ok(params)
    }
}

/// Typed reads of the declared values, each error naming the parameter.
struct ValueReader<'a> {
    values: &'a BTreeMap<String, ParamValue>,
}

impl ValueReader<'_> {
    fn get(&self, name: &str) -> ParamValue {
        self.values.get(name).cloned().unwrap_or(ParamValue::NotSet)
    }

    fn string(&self, name: &str) -> Result<String, String> {
        match self.get(name) {
            ParamValue::String(s) => Ok(s),
            other => Err(format!("`{name}` must be a string, got {other:?}")),
        }
    }

    fn double(&self, name: &str) -> Result<f64, String> {
        match self.get(name) {
            ParamValue::Double(v) if v.is_finite() => Ok(v),
            other => Err(format!("`{name}` must be a finite double, got {other:?}")),
        }
    }

    fn integer(&self, name: &str) -> Result<i64, String> {
        match self.get(name) {
            ParamValue::Integer(v) => Ok(v),
            other => Err(format!("`{name}` must be an integer, got {other:?}")),
        }
    }

    fn strings(&self, name: &str) -> Result<Vec<String>, String> {
        match self.get(name) {
            ParamValue::StringArray(v) => Ok(v),
            other => Err(format!("`{name}` must be a string array, got {other:?}")),
        }
    }

    /// An integer within the schema's range for `name` (0 = `None` where 0 means
    /// "default").
    fn ranged(&self, name: &str) -> Result<Option<i64>, String> {
        let range = spec_range(name);
        let zero_default = range.is_some_and(|r| r.zero_means_default);
        match self.integer(name)? {
            0 if zero_default => Ok(None),
            v if range.is_some_and(|r| (r.min..=r.max).contains(&(v as f64))) => Ok(Some(v)),
            v => Err(format!(
                "`{name}` must be {}in {}, got {v}",
                if zero_default { "0 (default) or " } else { "" },
                range.map_or("range".into(), |r| format!("{}..={}", r.min, r.max))
            )),
        }
    }

    fn flag(&self, name: &str) -> Result<bool, String> {
        boolean(name, &self.get(name))
    }
}

/// The values that describe the marker (`pattern_type` to `bitmaps`), validated.
struct PatternValues {
    pattern_type: MarkerKind,
    pattern_file: String,
    period: f64,
    metres_per_unit: f64,
    code_size: Option<i64>,
    code_depth: Option<i64>,
    window_size: Option<i64>,
    polarity: Option<vernier::Polarity>,
    bitmaps: Vec<String>,
}

impl PatternValues {
    fn read(read: &ValueReader) -> Result<PatternValues, String> {
        let pattern_type: MarkerKind = read
            .string("pattern_type")?
            .parse()
            .map_err(|e: vernier::Error| e.to_string())?;
        let pattern_file = read.string("pattern_file")?;
        let period = read.double("period")?;
        if period != 0.0 {
            // 0 = from the pattern file; any other value must be in the shared range.
            limits::check_period(period)
                .map_err(|e| format!("{e} (or 0 = from the pattern file)"))?;
        }
        let unit = read.string("period_unit")?;
        let metres_per_unit = UNITS
            .iter()
            .find(|(name, _)| *name == unit)
            .map(|(_, m)| *m)
            .ok_or_else(|| format!("`period_unit` must be nm, um, mm or m, got `{unit}`"))?;
        Ok(PatternValues {
            pattern_type,
            pattern_file,
            period,
            metres_per_unit,
            code_size: read.ranged("code_size")?,
            code_depth: read.ranged("code_depth")?,
            window_size: read.ranged("window_size")?,
            polarity: vernier::parse_polarity_setting(&read.string("polarity")?)
                .map_err(|e| e.to_string())?,
            bitmaps: read.strings("bitmaps")?,
        })
    }

    /// The detector settings, reading `pose_3d`, `focal_length_px` and `field_fit`.
    fn settings(
        &self,
        read: &ValueReader,
        pixel_size: Option<f64>,
    ) -> Result<DetectorSettings, String> {
        let pose_3d = read.flag("pose_3d")?;
        let focal_length_px = match read.double("focal_length_px")? {
            0.0 => None,
            v if (1.0..=MAX_FOCAL_LENGTH_PX).contains(&v) => Some(v),
            v => {
                return Err(format!(
                    "`focal_length_px` must be 0 (orthographic) or in 1..={MAX_FOCAL_LENGTH_PX:e} px, got {v}"
                ))
            }
        };
        Ok(DetectorSettings {
            pattern_type: self.pattern_type,
            pattern_file: (!self.pattern_file.is_empty())
                .then(|| PathBuf::from(&self.pattern_file)),
            period: (self.period > 0.0).then_some(self.period),
            code_size: self.code_size.map(|v| v as usize),
            code_depth: self.code_depth.map(|v| v as u32),
            window_size: self.window_size.map(|v| v as usize),
            polarity: self.polarity,
            bitmaps: self.bitmaps.iter().map(PathBuf::from).collect(),
            pose_3d,
            // Kept while pose_3d is off (a parameter set before the other), used with it.
            focal_length_px: focal_length_px.filter(|_| pose_3d),
            // true: each type's default (periodic grids keep the engine's planes: their
            // whole-image fit costs ~100× the engine); false: window planes for every type.
            field_fit: (!read.flag("field_fit")?).then_some(false),
            pixel_size,
        })
    }
}

/// The values that choose what is published and how (`marker_ids` to
/// `max_marker_publishers`), validated.
struct PublicationValues {
    marker_ids: Vec<u64>,
    relative_pairs: Vec<(u64, u64)>,
    min_quality: f64,
    camera_frame: String,
    marker_frame_prefix: String,
    publish_tf: bool,
    max_rate: f64,
    compressed_input: bool,
    max_marker_publishers: usize,
}

impl PublicationValues {
    fn read(read: &ValueReader) -> Result<PublicationValues, String> {
        let marker_ids = match read.get("marker_ids") {
            ParamValue::IntegerArray(ids) => ids
                .iter()
                .map(|&id| u64::try_from(id).map_err(|_| format!("`marker_ids`: negative id {id}")))
                .collect::<Result<Vec<u64>, String>>()?,
            other => {
                return Err(format!(
                    "`marker_ids` must be an integer array, got {other:?}"
                ))
            }
        };
        let relative_pairs = read
            .strings("relative_pairs")?
            .iter()
            .map(|pair| limits::parse_relative_pair(pair))
            .collect::<Result<Vec<_>, String>>()?;
        let min_quality = limits::check_quality("min_quality", read.double("min_quality")?)
            .map_err(|e| e.to_string())?;
        let camera_frame = read.string("camera_frame")?;
        let marker_frame_prefix = read.string("marker_frame_prefix")?;
        let publish_tf = read.flag("publish_tf")?;
        let max_rate =
            limits::check_rate("max_rate", read.double("max_rate")?).map_err(|e| e.to_string())?;
        let compressed_input = match read.string("image_transport")?.as_str() {
            "raw" => false,
            "compressed" => true,
            other => {
                return Err(format!(
                    "`image_transport` must be raw or compressed, got `{other}`"
                ))
            }
        };
        let image_qos = read.string("image_qos")?;
        if !["sensor_data", "reliable"].contains(&image_qos.as_str()) {
            return Err(format!(
                "`image_qos` must be sensor_data or reliable, got `{image_qos}`"
            ));
        }
        // Both ranges exclude 0-as-default, so `ranged` gives `Some`.
        let max_marker_publishers = read.ranged("max_marker_publishers")?.unwrap_or(1) as usize;
        Ok(PublicationValues {
            marker_ids,
            relative_pairs,
            min_quality,
            camera_frame,
            marker_frame_prefix,
            publish_tf,
            max_rate,
            compressed_input,
            max_marker_publishers,
        })
    }
}

/// The text of params/detector.yaml, generated from [`specs`]: each parameter with its
/// description (wrapped), unit and range as comments, and its [`ParamSpec::file_value`] or
/// default. A test checks that the shipped file is this text.
pub fn parameter_file_yaml() -> String {
    let mut out = String::from(PARAMETER_FILE_HEADER);
    out.push_str("/**:\n  ros__parameters:\n");
    for spec in specs() {
        let mut doc = spec.description.to_string();
        if let Some(r) = spec.range {
            let unit = if spec.unit.is_empty() {
                String::new()
            } else {
                format!(" {}", spec.unit)
            };
            let zero = if r.zero_means_default { " (or 0)" } else { "" };
            let span = if r.max >= 1e15 {
                format!("≥ {}", r.min)
            } else {
                format!("{}..={}", r.min, r.max)
            };
            doc.push_str(&format!(" Range: {span}{unit}{zero}."));
        }
        for line in wrap(&doc, 84) {
            out.push_str(&format!("    # {line}\n"));
        }
        let value = spec.file_value.as_ref().unwrap_or(&spec.default);
        match yaml_scalar(value) {
            Some(text) => out.push_str(&format!("    {}: {text}\n\n", spec.name)),
            // rcl cannot type an empty list: the default is left out.
            None => out.push_str(&format!("    # {}: []  (default: none)\n\n", spec.name)),
        }
    }
    out.truncate(out.trim_end().len());
    out.push('\n');
    out
}

const PARAMETER_FILE_HEADER: &str = "\
# Parameters of the vernier_ros `detector` node (standard ROS 2 parameter file).
# GENERATED from vernier-interface/src/params.rs (`specs`); edit that, then run
#   VERNIER_BLESS=1 cargo test -p vernier-interface parameter_file
#
#   ros2 run vernier_ros detector --ros-args --params-file params/detector.yaml
#   cargo run --release --bin detector -- --ros-args --params-file params/detector.yaml
#
# `/**` applies to the node whatever its name and namespace (default name: vernier_detector).
# Command-line `-p name:=value` overrides this file; names the node does not declare are
# ignored with a warning, as in rclcpp. Every parameter not marked read-only can be changed at
# run time with `ros2 param set /vernier_detector <name> <value>`: invalid values are rejected
# with a reason, accepted ones apply from the next frame.
#
# Outputs are SI: metres and radians, in the camera (optical) frame: x right, y down, z into
# the scene, origin at the centre pixel (columns div 2, rows div 2).
";

/// A value as a YAML flow scalar or sequence; `None` for an empty list.
fn yaml_scalar(value: &ParamValue) -> Option<String> {
    let string = |s: &str| {
        let plain = !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_alphanumeric() || "_./-".contains(c))
            && !s.starts_with(|c: char| c.is_ascii_digit() || c == '-')
            && !["true", "false", "yes", "no", "null", "on", "off"].contains(&s);
        if plain {
            s.to_string()
        } else {
            format!("\"{}\"", s.replace('\\', "\\\\").replace('"', "\\\""))
        }
    };
    let list = |items: Vec<String>| (!items.is_empty()).then(|| format!("[{}]", items.join(", ")));
    match value {
        ParamValue::NotSet => Some("~".into()),
        ParamValue::Boolean(b) => Some(b.to_string()),
        ParamValue::Integer(i) => Some(i.to_string()),
        ParamValue::Double(d) => Some(format!("{d:?}")),
        ParamValue::String(s) => Some(string(s)),
        ParamValue::ByteArray(a) => list(a.iter().map(u8::to_string).collect()),
        ParamValue::BooleanArray(a) => list(a.iter().map(bool::to_string).collect()),
        ParamValue::IntegerArray(a) => list(a.iter().map(i64::to_string).collect()),
        ParamValue::DoubleArray(a) => list(a.iter().map(|d| format!("{d:?}")).collect()),
        ParamValue::StringArray(a) => list(a.iter().map(|s| string(s)).collect()),
    }
}

/// `text` broken into lines of at most `width` characters, at spaces.
fn wrap(text: &str, width: usize) -> Vec<String> {
    let mut lines = Vec::new();
    let mut line = String::new();
    for word in text.split_whitespace() {
        if !line.is_empty() && line.chars().count() + 1 + word.chars().count() > width {
            lines.push(std::mem::take(&mut line));
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(word);
    }
    if !line.is_empty() {
        lines.push(line);
    }
    lines
}

/// The schema's range of `name`.
fn spec_range(name: &str) -> Option<ParamRange> {
    specs()
        .into_iter()
        .find(|s| s.name == name)
        .and_then(|s| s.range)
}

fn boolean(name: &str, value: &ParamValue) -> Result<bool, String> {
    match value {
        ParamValue::Boolean(b) => Ok(*b),
        other => Err(format!(
            "`{name}` has type boolean, got a {} value",
            other.type_name()
        )),
    }
}

/// `value` converted to the declared type where that loses nothing (integer → double, an
/// empty list → any list type); otherwise the type must match.
fn coerce(name: &str, declared: &ParamValue, value: &ParamValue) -> Result<ParamValue, String> {
    use ParamValue as V;
    match (declared, value) {
        (V::Double(_), V::Integer(i)) => Ok(V::Double(*i as f64)),
        (V::IntegerArray(_), V::StringArray(v)) if v.is_empty() => Ok(V::IntegerArray(vec![])),
        (V::StringArray(_), V::IntegerArray(v)) if v.is_empty() => Ok(V::StringArray(vec![])),
        (d, v) if std::mem::discriminant(d) == std::mem::discriminant(v) => Ok(v.clone()),
        (d, v) => Err(format!(
            "`{name}` has type {}, got a {} value",
            d.type_name(),
            v.type_name()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn defaults_with(overrides: &[(&str, ParamValue)]) -> Result<NodeParams, String> {
        let owned: Vec<(String, ParamValue)> = overrides
            .iter()
            .map(|(n, v)| (n.to_string(), v.clone()))
            .collect();
        NodeParams::from_overrides(&owned).map(|s| s.params)
    }

    #[test]
    fn defaults_need_a_period() {
        let err = defaults_with(&[]).err().unwrap_or_default();
        assert!(err.contains("period"), "{err}");
        let p = defaults_with(&[("period", ParamValue::Integer(4))]);
        let p = p.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.settings.period, Some(4.0));
        assert_eq!(p.metres_per_unit, 1e-6);
        assert!(p.tracks(12));
        assert!(p.publish_tf);
    }

    #[test]
    fn the_parameter_file_is_generated_from_the_schema() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../params/detector.yaml");
        let generated = parameter_file_yaml();
        if std::env::var_os("VERNIER_BLESS").is_some() {
            std::fs::write(&path, &generated).unwrap_or_else(|e| panic!("{e}"));
        }
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            text == generated,
            "params/detector.yaml is out of date: run VERNIER_BLESS=1 cargo test -p \
             vernier-interface parameter_file"
        );
        // The file parses as the node reads it, and gives a valid set.
        let values = crate::ros_args::parse_params_file(&text, "/", "vernier_detector")
            .unwrap_or_else(|e| panic!("{e}"));
        let startup = NodeParams::from_overrides(&values).unwrap_or_else(|e| panic!("{e}"));
        assert!(startup.ignored.is_empty(), "{:?}", startup.ignored);
        assert_eq!(startup.params.settings.period, Some(10.0));
    }

    #[test]
    fn ranges_in_the_schema_are_the_ones_enforced() {
        let base =
            defaults_with(&[("period", ParamValue::Double(4.0))]).unwrap_or_else(|e| panic!("{e}"));
        for spec in specs() {
            let Some(r) = spec.range else { continue };
            let value = |v: f64| match spec.default {
                ParamValue::Integer(_) => ParamValue::Integer(v as i64),
                _ => ParamValue::Double(v),
            };
            let integer = matches!(spec.default, ParamValue::Integer(_));
            let below = if integer {
                r.min - 1.0
            } else {
                r.min * 0.5 - 1e-3
            };
            // HP code widths must also be ≡ 1 (mod 4): test with an admissible one.
            let inside = if spec.name == "code_size" {
                33.0
            } else {
                r.min
            };
            base.with(spec.name, &value(inside))
                .unwrap_or_else(|e| panic!("{} = {inside}: {e}", spec.name));
            if !(r.zero_means_default && below <= 0.0 && below > -1.0) {
                assert!(
                    base.with(spec.name, &value(below)).is_err(),
                    "{} = {below} accepted",
                    spec.name
                );
            }
            if r.max < 1e15 {
                let above = if integer { r.max + 1.0 } else { r.max * 2.0 };
                assert!(
                    base.with(spec.name, &value(above)).is_err(),
                    "{}",
                    spec.name
                );
            }
        }
    }

    #[test]
    fn startup_ignores_foreign_names_and_takes_sim_time_and_qos() {
        let overrides = vec![
            ("period".to_string(), ParamValue::Double(4.0)),
            ("use_sim_time".to_string(), ParamValue::Boolean(true)),
            (
                "some_other_node_setting".to_string(),
                ParamValue::Integer(3),
            ),
            (
                "qos_overrides./image.subscription.reliability".to_string(),
                ParamValue::String("reliable".into()),
            ),
            (
                "qos_overrides./image.subscription.depth".to_string(),
                ParamValue::Integer(3),
            ),
            (
                "qos_overrides./tf.publisher.depth".to_string(),
                ParamValue::Integer(3),
            ),
        ];
        let startup = NodeParams::from_overrides(&overrides).unwrap_or_else(|e| panic!("{e}"));
        let p = &startup.params;
        assert!(p.use_sim_time);
        assert_eq!(startup.ignored.len(), 2, "{:?}", startup.ignored);
        let qos = p.image_qos("/image");
        assert_eq!(qos.reliability, QosReliability::Reliable);
        assert_eq!(qos.depth, 3);
        assert_eq!(p.image_qos("/other"), ImageQos::SENSOR_DATA);
        assert_eq!(p.unused_qos_overrides("/image").len(), 0);
        // Bad values of taken names are errors, not warnings.
        for (name, value) in [
            ("use_sim_time", ParamValue::Integer(1)),
            (
                "qos_overrides./image.subscription.reliability",
                ParamValue::String("sometimes".into()),
            ),
            (
                "qos_overrides./image.subscription.depth",
                ParamValue::Integer(0),
            ),
        ] {
            let mut o = overrides[..1].to_vec();
            o.push((name.to_string(), value));
            assert!(NodeParams::from_overrides(&o).is_err(), "{name}");
        }
        // At run time: use_sim_time can change; read-only and unknown names cannot.
        let q = p
            .with("use_sim_time", &ParamValue::Boolean(false))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(!q.use_sim_time);
        assert_eq!(q.image_qos("/image").depth, 3);
        let e = p
            .with("image_transport", &ParamValue::String("compressed".into()))
            .err()
            .unwrap_or_default();
        assert!(e.contains("read-only"), "{e}");
        assert!(p
            .with("some_other_node_setting", &ParamValue::Integer(3))
            .is_err());
    }

    #[test]
    fn every_parameter_is_declared_once_with_a_description() {
        let specs = specs();
        for s in &specs {
            assert!(!s.description.is_empty(), "{}", s.name);
            assert_eq!(specs.iter().filter(|o| o.name == s.name).count(), 1);
        }
        let p =
            defaults_with(&[("period", ParamValue::Double(4.0))]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.values().len(), specs.len());
    }

    #[test]
    fn updates_are_validated_with_reasons() {
        let p =
            defaults_with(&[("period", ParamValue::Double(4.0))]).unwrap_or_else(|e| panic!("{e}"));
        let cases: Vec<(&str, ParamValue, &str)> = vec![
            ("period", ParamValue::Double(-1.0), "period"),
            ("period", ParamValue::String("4".into()), "type"),
            ("period", ParamValue::NotSet, "type"),
            (
                "period_unit",
                ParamValue::String("inch".into()),
                "period_unit",
            ),
            ("polarity", ParamValue::String("grey".into()), "polarity"),
            (
                "pattern_type",
                ParamValue::String("qr".into()),
                "pattern_type",
            ),
            (
                "relative_pairs",
                ParamValue::StringArray(vec!["1-2".into()]),
                "a:b",
            ),
            (
                "relative_pairs",
                ParamValue::StringArray(vec!["1:1".into()]),
                "itself",
            ),
            ("marker_ids", ParamValue::IntegerArray(vec![-3]), "negative"),
            ("min_quality", ParamValue::Double(1.5), "min_quality"),
            ("max_rate", ParamValue::Double(-2.0), "max_rate"),
            ("code_depth", ParamValue::Integer(40), "code_depth"),
            ("period", ParamValue::Double(5e-324), "period"),
            ("code_size", ParamValue::Integer(1_000_001), "code_size"),
            (
                "window_size",
                ParamValue::Integer(4_294_967_295),
                "window_size",
            ),
            ("max_rate", ParamValue::Double(1e300), "max_rate"),
            (
                "max_image_pixels",
                ParamValue::Integer(0),
                "max_image_pixels",
            ),
            (
                "pattern_file",
                ParamValue::String("/nonexistent.json".into()),
                "nonexistent",
            ),
            ("no_such_parameter", ParamValue::Boolean(true), "unknown"),
        ];
        for (name, value, reason) in cases {
            let err = p.with(name, &value).err().unwrap_or_default();
            assert!(
                err.contains(reason),
                "{name}={value:?}: `{err}` lacks `{reason}`"
            );
        }
        let q = p
            .with(
                "relative_pairs",
                &ParamValue::StringArray(vec!["0:1".into(), " 2 : 5".into()]),
            )
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.relative_pairs, vec![(0, 1), (2, 5)]);
        let q = q
            .with("period", &ParamValue::Double(8.0))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.settings.period, Some(8.0));
        assert_eq!(q.detector_config().map(|c| c.period()), Ok(8.0));
        let q = q
            .with("period_unit", &ParamValue::String("nm".into()))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.metres_per_unit, 1e-9);
        let q = q
            .with("marker_ids", &ParamValue::StringArray(vec![]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(q.marker_ids.is_empty());
        let q = q
            .with("marker_ids", &ParamValue::IntegerArray(vec![3]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(q.tracks(3) && !q.tracks(4));
    }
}
