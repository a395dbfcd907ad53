//! Reads the detector node's ROS 2 parameter file (params/detector.yaml) into detector
//! settings, so that `vernier bag` replays a recording with the node's exact configuration.
//!
//! Only the parameters that change the measurement are used: `pattern_type`,
//! `pattern_file`, `period`, `period_unit`, `code_size`, `code_depth`, `window_size`,
//! `polarity`, `bitmaps`, `marker_ids`, `min_quality`, `camera_frame` and
//! `max_image_pixels`; the others (TF, rate) are checked but do not change a replay. Zero /
//! empty values mean "default", as in the node. Every value is validated with the node's
//! ranges ([`vernier::limits`]), and a name the node does not declare is an error, so a file
//! is accepted here exactly when the node accepts it. The YAML is read with the limits of
//! [`vernier::limits::load_yaml`] (size, alias expansion, depth).

use std::path::{Path, PathBuf};

use vernier::detector::{DetectorSettings, MarkerKind};
use yaml_rust2::Yaml;

/// Settings of a replay.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReplayParams {
    /// Detector settings.
    pub settings: DetectorSettings,
    /// Metres per pattern unit (`period_unit`: nm, um, mm, m; default µm).
    pub metres_per_unit: f64,
    /// Marker IDs kept; empty = all.
    pub marker_ids: Vec<u64>,
    /// Markers below this quality are dropped.
    pub min_quality: f64,
    /// `frame_id` of the outputs; empty = the image's.
    pub camera_frame: String,
    /// Largest image processed, pixels (`max_image_pixels`).
    pub max_pixels: u64,
}

impl ReplayParams {
    /// Defaults of the node: periodic markers, µm, every ID.
    pub fn new() -> Self {
        ReplayParams {
            metres_per_unit: 1e-6,
            max_pixels: vernier::limits::DEFAULT_MAX_PIXELS,
            ..ReplayParams::default()
        }
    }
}

/// The `ros__parameters` mapping of the file: the `/**` entry if present, else the first
/// node entry; a flat mapping without node level is accepted too.
fn parameters(doc: &Yaml) -> Option<&yaml_rust2::yaml::Hash> {
    let top = doc.as_hash()?;
    let key = Yaml::String("ros__parameters".into());
    let wildcard = Yaml::String("/**".into());
    let node = top
        .get(&wildcard)
        .and_then(|n| n.as_hash())
        .filter(|n| n.contains_key(&key))
        .or_else(|| {
            top.values()
                .filter_map(|n| n.as_hash())
                .find(|n| n.contains_key(&key))
        });
    match node {
        Some(n) => n.get(&key).and_then(|p| p.as_hash()),
        None => Some(top),
    }
}

/// Reads a parameter file. Relative `pattern_file` and `bitmaps` paths are taken relative to
/// the current directory, as the node does.
pub fn read_params(path: &Path) -> Result<ReplayParams, String> {
    let text = vernier::limits::read_text_bounded(
        path,
        vernier::limits::MAX_PARAM_FILE_BYTES,
        "parameter file",
    )?;
    parse_params(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Parses parameter-file text.
pub fn parse_params(text: &str) -> Result<ReplayParams, String> {
    let docs = vernier::limits::load_yaml(text).map_err(|e| format!("bad YAML: {e}"))?;
    let mut out = ReplayParams::new();
    let Some(params) = docs.first().and_then(parameters) else {
        return Ok(out);
    };
    for (key, value) in params {
        let Some(name) = key.as_str() else {
            return Err(format!("parameter names must be strings, got {key:?}"));
        };
        if !vernier::limits::NODE_PARAMETERS.contains(&name) {
            return Err(format!(
                "unknown parameter `{name}` (the detector node declares: {})",
                vernier::limits::NODE_PARAMETERS.join(", ")
            ));
        }
        let wrong =
            |expected: &str| format!("parameter `{name}` must be {expected}, got {value:?}");
        let number = || value.as_f64().or_else(|| value.as_i64().map(|v| v as f64));
        let count = || -> Result<Option<u64>, String> {
            match value.as_i64() {
                Some(0) => Ok(None),
                Some(v) if v > 0 => Ok(Some(v as u64)),
                _ => Err(wrong("a non-negative integer")),
            }
        };
        let s = &mut out.settings;
        match name {
            "pattern_type" => {
                let text = value.as_str().ok_or_else(|| wrong("a string"))?;
                s.pattern_type = text.parse::<MarkerKind>().map_err(|e| e.to_string())?;
            }
            "pattern_file" => {
                let text = value.as_str().ok_or_else(|| wrong("a string"))?;
                s.pattern_file = (!text.is_empty()).then(|| PathBuf::from(text));
            }
            "period" => {
                let v = number()
                    .filter(|v| *v >= 0.0)
                    .ok_or_else(|| wrong("a number ≥ 0"))?;
                s.period = (v > 0.0).then_some(v);
            }
            "period_unit" => {
                out.metres_per_unit = match value.as_str() {
                    Some("nm") => 1e-9,
                    Some("um") | Some("µm") => 1e-6,
                    Some("mm") => 1e-3,
                    Some("m") => 1.0,
                    _ => return Err(wrong("nm, um, mm or m")),
                };
            }
            "code_size" => s.code_size = count()?.map(|v| v as usize),
            "code_depth" => s.code_depth = count()?.map(|v| v as u32),
            "window_size" => s.window_size = count()?.map(|v| v as usize),
            "polarity" => {
                let text = value
                    .as_str()
                    .ok_or_else(|| wrong("`auto`, `bright` or `dark`"))?;
                s.polarity = vernier::parse_polarity_setting(text).map_err(|e| e.to_string())?;
            }
            "bitmaps" => {
                let list = value.as_vec().ok_or_else(|| wrong("a list of files"))?;
                s.bitmaps = list
                    .iter()
                    .map(|v| {
                        v.as_str()
                            .map(PathBuf::from)
                            .ok_or_else(|| wrong("a list of files"))
                    })
                    .collect::<Result<_, _>>()?;
            }
            "marker_ids" => {
                let list = value.as_vec().ok_or_else(|| wrong("a list of IDs"))?;
                out.marker_ids = list
                    .iter()
                    .map(|v| {
                        v.as_i64()
                            .and_then(|i| u64::try_from(i).ok())
                            .ok_or_else(|| wrong("a list of IDs ≥ 0"))
                    })
                    .collect::<Result<_, _>>()?;
            }
            "min_quality" => {
                let v = number().ok_or_else(|| wrong("a number"))?;
                out.min_quality =
                    vernier::limits::check_quality("min_quality", v).map_err(|e| e.to_string())?;
            }
            "camera_frame" => {
                out.camera_frame = value.as_str().ok_or_else(|| wrong("a string"))?.to_string();
            }
            "marker_frame_prefix" => {
                value.as_str().ok_or_else(|| wrong("a string"))?;
            }
            "publish_tf" => {
                value.as_bool().ok_or_else(|| wrong("true or false"))?;
            }
            "max_rate" => {
                let v = number().ok_or_else(|| wrong("a number"))?;
                vernier::limits::check_rate("max_rate", v).map_err(|e| e.to_string())?;
            }
            "relative_pairs" => {
                let list = value
                    .as_vec()
                    .ok_or_else(|| wrong("a list of \"a:b\" pairs"))?;
                for pair in list {
                    let text = pair
                        .as_str()
                        .ok_or_else(|| wrong("a list of \"a:b\" pairs"))?;
                    vernier::limits::parse_relative_pair(text)?;
                }
            }
            "max_image_pixels" => {
                let v = value
                    .as_i64()
                    .and_then(|v| u64::try_from(v).ok())
                    .ok_or_else(|| wrong("a pixel count ≥ 1"))?;
                out.max_pixels = vernier::limits::check_max_pixels(v).map_err(|e| e.to_string())?;
            }
            // Every name of NODE_PARAMETERS is handled above.
            _ => {}
        }
    }
    out.settings.validate().map_err(|e| e.to_string())?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_node_parameter_file() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../params/detector.yaml");
        let p = read_params(&path).unwrap();
        assert_eq!(p.settings.pattern_type, MarkerKind::Periodic);
        assert_eq!(p.settings.period, Some(10.0));
        assert_eq!(p.metres_per_unit, 1e-6);
    }

    #[test]
    fn parses_values_and_rejects_bad_ones() {
        let p = parse_params(
            "/vernier_detector:\n  ros__parameters:\n    pattern_type: hpcode\n    period: 15\n    \
             period_unit: nm\n    code_size: 33\n    polarity: dark\n    marker_ids: [0, 4]\n    \
             pattern_file: ''\n    publish_tf: true\n",
        )
        .unwrap();
        assert_eq!(p.settings.pattern_type, MarkerKind::HpCode);
        assert_eq!(p.settings.period, Some(15.0));
        assert_eq!(p.settings.code_size, Some(33));
        assert_eq!(p.settings.pattern_file, None);
        assert_eq!(p.metres_per_unit, 1e-9);
        assert_eq!(p.marker_ids, [0, 4]);
        let flat = parse_params("period: 8.0\n").unwrap();
        assert_eq!(flat.settings.period, Some(8.0));
        for bad in [
            "period: -1",
            "period: 5e-324",
            "period_unit: inch",
            "code_size: x",
            "code_size: 1000001",
            "window_size: 4294967295",
            "marker_ids: [-1]",
            "min_quality: 2",
            "max_rate: -5",
            "relative_pairs: ['1-2']",
            "relative_pairs: ['1:1']",
            "no_such_parameter: 1",
            "max_image_pixels: 0",
        ] {
            let e = parse_params(bad).unwrap_err();
            assert!(
                e.contains("parameter `") || e.contains("relative_pairs"),
                "{bad}: {e}"
            );
        }
        let p = parse_params("max_image_pixels: 1000\nmax_rate: 30\npublish_tf: false\n").unwrap();
        assert_eq!(p.max_pixels, 1000);
        // Billion laughs: refused before any alias is expanded.
        let mut bomb = String::from("a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n");
        for i in 1..12 {
            let refs = vec![format!("*a{}", i - 1); 10].join(", ");
            bomb.push_str(&format!("a{i}: &a{i} [{refs}]\n"));
        }
        let e = parse_params(&bomb).unwrap_err();
        assert!(e.contains("nodes"), "{e}");
    }
}
