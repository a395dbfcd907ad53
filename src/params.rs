//! The node's parameters: declaration (name, type, default, description), validation of
//! every value with a reason, and the mapping onto [`vernier::detector::DetectorSettings`].
//!
//! [`NodeParams`] is the typed, validated set. A change arrives as `(name, value)`;
//! [`NodeParams::with`] returns the new set or the reason it is rejected, so the same code
//! serves the command line, parameter files and the `ros2 param set` services.

use ros2_client::ParameterValue;
use std::collections::BTreeMap;
use std::path::PathBuf;
use vernier::detector::{DetectorConfig, DetectorSettings, MarkerKind};
use vernier::{limits, Detector};

/// One declared parameter.
#[derive(Clone, Debug)]
pub struct ParamSpec {
    /// Parameter name.
    pub name: &'static str,
    /// Default value (its variant is the parameter's type).
    pub default: ParameterValue,
    /// What it does, with units.
    pub description: &'static str,
}

/// Every parameter of the node, in documentation order (params/detector.yaml follows it).
pub fn specs() -> Vec<ParamSpec> {
    use ParameterValue as V;
    let spec = |name, default, description| ParamSpec {
        name,
        default,
        description,
    };
    vec![
        spec(
            "pattern_type",
            V::String("periodic".into()),
            "Marker family: periodic, hpcode, stamp or megarena (a pattern file's class wins).",
        ),
        spec(
            "pattern_file",
            V::String(String::new()),
            "JSON pattern file (PeriodicPattern, HPCodePattern, ...); empty = none.",
        ),
        spec(
            "period",
            V::Double(0.0),
            "Physical period of the dot grid, in `period_unit`; 0 = take it from the pattern file.",
        ),
        spec(
            "period_unit",
            V::String("um".into()),
            "Length unit of `period` and of the pattern file: nm, um, mm or m. Outputs are metres.",
        ),
        spec(
            "code_size",
            V::Integer(0),
            "HP code width in half-period cells (33, 37, ...); 0 = pattern file or default.",
        ),
        spec(
            "code_depth",
            V::Integer(0),
            "Megarena LFSR bit depth (4..12); 0 = pattern file or default.",
        ),
        spec(
            "window_size",
            V::Integer(0),
            "Side of the square window analysed around each marker, pixels; 0 = default.",
        ),
        spec(
            "polarity",
            V::String("auto".into()),
            "Dot polarity: auto (per marker for HP codes and stamps, bright for periodic and Megarena), bright (bright dots on dark) or dark (dark dots on bright).",
        ),
        spec(
            "bitmaps",
            V::StringArray(Vec::new()),
            "Stamp bitmap PNG files (1 = dot), in ID order.",
        ),
        spec(
            "marker_ids",
            V::IntegerArray(Vec::new()),
            "IDs to publish; empty = every marker found.",
        ),
        spec(
            "relative_pairs",
            V::StringArray(Vec::new()),
            "Pairs \"a:b\": publish the pose of marker b in marker a's frame.",
        ),
        spec(
            "min_quality",
            V::Double(0.0),
            "Markers whose quality (fraction of variance explained, [0, 1]) is below are ignored.",
        ),
        spec(
            "camera_frame",
            V::String(String::new()),
            "Frame of the output poses; empty = the image's header.frame_id.",
        ),
        spec(
            "marker_frame_prefix",
            V::String("vernier_marker_".into()),
            "TF child frame of marker <id> is <prefix><id>.",
        ),
        spec(
            "publish_tf",
            V::Boolean(true),
            "Broadcast camera → marker transforms on /tf.",
        ),
        spec(
            "max_rate",
            V::Double(0.0),
            "Highest processing rate, Hz; frames arriving faster are skipped; 0 = no limit.",
        ),
        spec(
            "max_image_pixels",
            V::Integer(vernier::limits::DEFAULT_MAX_PIXELS as i64),
            "Largest image processed, pixels (width × height); larger frames are rejected as bad images.",
        ),
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
    values: BTreeMap<String, ParameterValue>,
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
}

impl NodeParams {
    /// The defaults with `overrides` applied in order (later wins). Errors name the parameter.
    pub fn from_overrides(overrides: &[(String, ParameterValue)]) -> Result<NodeParams, String> {
        let mut values: BTreeMap<String, ParameterValue> = specs()
            .into_iter()
            .map(|s| (s.name.to_string(), s.default))
            .collect();
        for (name, value) in overrides {
            let declared = values
                .get(name)
                .ok_or_else(|| format!("unknown parameter `{name}`"))?;
            let value = coerce(name, declared, value)?;
            values.insert(name.clone(), value);
        }
        Self::from_values(values)
    }

    /// The values to declare on the ROS node, by name.
    pub fn values(&self) -> &BTreeMap<String, ParameterValue> {
        &self.values
    }

    /// The parameter set with `name` changed to `value`, or why the change is rejected.
    pub fn with(&self, name: &str, value: &ParameterValue) -> Result<NodeParams, String> {
        let declared = self
            .values
            .get(name)
            .ok_or_else(|| format!("unknown parameter `{name}`"))?;
        let value = coerce(name, declared, value)?;
        let mut values = self.values.clone();
        values.insert(name.to_string(), value);
        Self::from_values(values)
    }

    /// Builds the detector configuration (reads the pattern file).
    pub fn detector_config(&self) -> Result<DetectorConfig, String> {
        self.settings.to_config().map_err(|e| e.to_string())
    }

    /// Builds a detector for these settings.
    pub fn build_detector(&self) -> Result<(Detector, DetectorConfig), String> {
        let config = self.detector_config()?;
        let detector = Detector::new(config.clone()).map_err(|e| e.to_string())?;
        Ok((detector, config))
    }

    /// Whether marker `id` is published.
    pub fn tracks(&self, id: u64) -> bool {
        self.marker_ids.is_empty() || self.marker_ids.contains(&id)
    }

    fn from_values(values: BTreeMap<String, ParameterValue>) -> Result<NodeParams, String> {
        let get = |name: &str| values.get(name).cloned().unwrap_or(ParameterValue::NotSet);
        let string = |name: &str| match get(name) {
            ParameterValue::String(s) => Ok(s),
            other => Err(format!("`{name}` must be a string, got {other:?}")),
        };
        let double = |name: &str| match get(name) {
            ParameterValue::Double(v) if v.is_finite() => Ok(v),
            other => Err(format!("`{name}` must be a finite double, got {other:?}")),
        };
        let integer = |name: &str| match get(name) {
            ParameterValue::Integer(v) => Ok(v),
            other => Err(format!("`{name}` must be an integer, got {other:?}")),
        };
        let strings = |name: &str| match get(name) {
            ParameterValue::StringArray(v) => Ok(v),
            other => Err(format!("`{name}` must be a string array, got {other:?}")),
        };
        let optional_count = |name: &str, min: i64, max: i64| -> Result<Option<i64>, String> {
            match integer(name)? {
                0 => Ok(None),
                v if (min..=max).contains(&v) => Ok(Some(v)),
                v => Err(format!(
                    "`{name}` must be 0 (default) or in {min}..={max}, got {v}"
                )),
            }
        };

        let pattern_type: MarkerKind = string("pattern_type")?
            .parse()
            .map_err(|e: vernier::Error| e.to_string())?;
        let pattern_file = string("pattern_file")?;
        let period = double("period")?;
        if period != 0.0 {
            // 0 = from the pattern file; any other value must be in the shared range.
            limits::check_period(period)
                .map_err(|e| format!("{e} (or 0 = from the pattern file)"))?;
        }
        let unit = string("period_unit")?;
        let metres_per_unit = UNITS
            .iter()
            .find(|(name, _)| *name == unit)
            .map(|(_, m)| *m)
            .ok_or_else(|| format!("`period_unit` must be nm, um, mm or m, got `{unit}`"))?;
        let code_size = optional_count(
            "code_size",
            limits::MIN_CODE_SIZE as i64,
            limits::MAX_CODE_SIZE as i64,
        )?;
        let code_depth = optional_count(
            "code_depth",
            limits::MIN_CODE_DEPTH as i64,
            limits::MAX_CODE_DEPTH as i64,
        )?;
        let window_size = optional_count(
            "window_size",
            limits::MIN_WINDOW_SIZE as i64,
            limits::MAX_WINDOW_SIZE as i64,
        )?;
        let polarity =
            vernier::parse_polarity_setting(&string("polarity")?).map_err(|e| e.to_string())?;
        let bitmaps = strings("bitmaps")?;
        let marker_ids = match get("marker_ids") {
            ParameterValue::IntegerArray(ids) => ids
                .iter()
                .map(|&id| u64::try_from(id).map_err(|_| format!("`marker_ids`: negative id {id}")))
                .collect::<Result<Vec<u64>, String>>()?,
            other => {
                return Err(format!(
                    "`marker_ids` must be an integer array, got {other:?}"
                ))
            }
        };
        let relative_pairs = strings("relative_pairs")?
            .iter()
            .map(|pair| limits::parse_relative_pair(pair))
            .collect::<Result<Vec<_>, String>>()?;
        let min_quality = limits::check_quality("min_quality", double("min_quality")?)
            .map_err(|e| e.to_string())?;
        let camera_frame = string("camera_frame")?;
        let marker_frame_prefix = string("marker_frame_prefix")?;
        let publish_tf = match get("publish_tf") {
            ParameterValue::Boolean(b) => b,
            other => return Err(format!("`publish_tf` must be a bool, got {other:?}")),
        };
        let max_rate =
            limits::check_rate("max_rate", double("max_rate")?).map_err(|e| e.to_string())?;
        let max_image_pixels = u64::try_from(integer("max_image_pixels")?)
            .map_err(|_| "`max_image_pixels` must be ≥ 1 pixel".to_string())
            .and_then(|v| limits::check_max_pixels(v).map_err(|e| e.to_string()))?;

        let settings = DetectorSettings {
            pattern_type,
            pattern_file: (!pattern_file.is_empty()).then(|| PathBuf::from(&pattern_file)),
            period: (period > 0.0).then_some(period),
            code_size: code_size.map(|v| v as usize),
            code_depth: code_depth.map(|v| v as u32),
            window_size: window_size.map(|v| v as usize),
            polarity,
            bitmaps: bitmaps.iter().map(PathBuf::from).collect(),
        };
        let params = NodeParams {
            values,
            settings,
            metres_per_unit,
            marker_ids,
            relative_pairs,
            min_quality,
            camera_frame,
            marker_frame_prefix,
            publish_tf,
            max_rate,
            max_image_pixels,
        };
        // The whole configuration must make a detector (period given, pattern file readable,
        // marker type implemented...).
        params.build_detector()?;
        Ok(params)
    }
}

/// `value` converted to the declared type where that loses nothing (integer → double, an
/// empty list → any list type); otherwise the type must match.
fn coerce(
    name: &str,
    declared: &ParameterValue,
    value: &ParameterValue,
) -> Result<ParameterValue, String> {
    use ParameterValue as V;
    match (declared, value) {
        (V::Double(_), V::Integer(i)) => Ok(V::Double(*i as f64)),
        (V::IntegerArray(_), V::StringArray(v)) if v.is_empty() => Ok(V::IntegerArray(vec![])),
        (V::StringArray(_), V::IntegerArray(v)) if v.is_empty() => Ok(V::StringArray(vec![])),
        (d, v) if std::mem::discriminant(d) == std::mem::discriminant(v) => Ok(v.clone()),
        (d, v) => Err(format!(
            "`{name}` has type {:?}, got a {:?} value",
            d.to_parameter_type(),
            v.to_parameter_type()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn defaults_with(overrides: &[(&str, ParameterValue)]) -> Result<NodeParams, String> {
        let owned: Vec<(String, ParameterValue)> = overrides
            .iter()
            .map(|(n, v)| (n.to_string(), v.clone()))
            .collect();
        NodeParams::from_overrides(&owned)
    }

    #[test]
    fn defaults_need_a_period() {
        let err = defaults_with(&[]).err().unwrap_or_default();
        assert!(err.contains("period"), "{err}");
        let p = defaults_with(&[("period", ParameterValue::Integer(4))]);
        let p = p.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.settings.period, Some(4.0));
        assert_eq!(p.metres_per_unit, 1e-6);
        assert!(p.tracks(12));
        assert!(p.publish_tf);
    }

    #[test]
    fn the_parameter_file_documents_every_parameter() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("params/detector.yaml");
        let text = std::fs::read_to_string(path).unwrap_or_default();
        let values = crate::ros_args::parse_params_file(&text, "/", "vernier_detector")
            .unwrap_or_else(|e| panic!("{e}"));
        let mut names: Vec<&str> = values.iter().map(|(n, _)| n.as_str()).collect();
        // Empty-list defaults cannot be written in ROS parameter files: they are commented.
        names.extend(["bitmaps", "relative_pairs"]);
        names.sort_unstable();
        let mut declared: Vec<&str> = specs().iter().map(|s| s.name).collect();
        declared.sort_unstable();
        assert_eq!(names, declared);
        NodeParams::from_overrides(&values).unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn the_core_crate_lists_every_parameter() {
        // `vernier bag --params` accepts exactly these names (vernier::limits).
        let names: Vec<&str> = specs().iter().map(|s| s.name).collect();
        assert_eq!(names, limits::NODE_PARAMETERS);
    }

    #[test]
    fn every_parameter_is_declared_once_with_a_description() {
        let specs = specs();
        for s in &specs {
            assert!(!s.description.is_empty(), "{}", s.name);
            assert_eq!(specs.iter().filter(|o| o.name == s.name).count(), 1);
        }
        let p = defaults_with(&[("period", ParameterValue::Double(4.0))])
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.values().len(), specs.len());
    }

    #[test]
    fn updates_are_validated_with_reasons() {
        let p = defaults_with(&[("period", ParameterValue::Double(4.0))])
            .unwrap_or_else(|e| panic!("{e}"));
        let cases: Vec<(&str, ParameterValue, &str)> = vec![
            ("period", ParameterValue::Double(-1.0), "period"),
            ("period", ParameterValue::String("4".into()), "type"),
            ("period", ParameterValue::NotSet, "type"),
            (
                "period_unit",
                ParameterValue::String("inch".into()),
                "period_unit",
            ),
            (
                "polarity",
                ParameterValue::String("grey".into()),
                "polarity",
            ),
            (
                "pattern_type",
                ParameterValue::String("qr".into()),
                "pattern_type",
            ),
            (
                "relative_pairs",
                ParameterValue::StringArray(vec!["1-2".into()]),
                "a:b",
            ),
            (
                "relative_pairs",
                ParameterValue::StringArray(vec!["1:1".into()]),
                "itself",
            ),
            (
                "marker_ids",
                ParameterValue::IntegerArray(vec![-3]),
                "negative",
            ),
            ("min_quality", ParameterValue::Double(1.5), "min_quality"),
            ("max_rate", ParameterValue::Double(-2.0), "max_rate"),
            ("code_depth", ParameterValue::Integer(40), "code_depth"),
            ("period", ParameterValue::Double(5e-324), "period"),
            ("code_size", ParameterValue::Integer(1_000_001), "code_size"),
            (
                "window_size",
                ParameterValue::Integer(4_294_967_295),
                "window_size",
            ),
            ("max_rate", ParameterValue::Double(1e300), "max_rate"),
            (
                "max_image_pixels",
                ParameterValue::Integer(0),
                "max_image_pixels",
            ),
            (
                "pattern_file",
                ParameterValue::String("/nonexistent.json".into()),
                "nonexistent",
            ),
            (
                "no_such_parameter",
                ParameterValue::Boolean(true),
                "unknown",
            ),
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
                &ParameterValue::StringArray(vec!["0:1".into(), " 2 : 5".into()]),
            )
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.relative_pairs, vec![(0, 1), (2, 5)]);
        let q = q
            .with("period", &ParameterValue::Double(8.0))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.settings.period, Some(8.0));
        assert_eq!(q.detector_config().map(|c| c.period()), Ok(8.0));
        let q = q
            .with("period_unit", &ParameterValue::String("nm".into()))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(q.metres_per_unit, 1e-9);
        let q = q
            .with("marker_ids", &ParameterValue::StringArray(vec![]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(q.marker_ids.is_empty());
        let q = q
            .with("marker_ids", &ParameterValue::IntegerArray(vec![3]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(q.tracks(3) && !q.tracks(4));
    }
}
