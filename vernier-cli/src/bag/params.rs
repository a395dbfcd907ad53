//! Reads the detector node's ROS 2 parameter file (params/detector.yaml) into detector
//! settings, so that `vernier bag` replays a recording with the node's exact configuration.
//!
//! Only the parameters that change the measurement are used: `pattern_type`,
//! `pattern_file`, `period`, `period_unit`, `code_size`, `code_depth`, `window_size`,
//! `polarity`, `bitmaps`, `marker_ids`, `min_quality` and `camera_frame`; the others
//! (topics, QoS, TF) are ignored. Zero / empty values mean "default", as in the node.

use std::path::{Path, PathBuf};

use vernier::detector::{DetectorSettings, MarkerKind};
use yaml_rust2::{Yaml, YamlLoader};

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
}

impl ReplayParams {
    /// Defaults of the node: periodic markers, µm, every ID.
    pub fn new() -> Self {
        ReplayParams {
            metres_per_unit: 1e-6,
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
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_params(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Parses parameter-file text.
pub fn parse_params(text: &str) -> Result<ReplayParams, String> {
    let docs = YamlLoader::load_from_str(text).map_err(|e| format!("bad YAML: {e}"))?;
    let mut out = ReplayParams::new();
    let Some(params) = docs.first().and_then(parameters) else {
        return Ok(out);
    };
    for (key, value) in params {
        let Some(name) = key.as_str() else { continue };
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
                out.min_quality = number().ok_or_else(|| wrong("a number"))?;
            }
            "camera_frame" => {
                out.camera_frame = value.as_str().ok_or_else(|| wrong("a string"))?.to_string();
            }
            _ => {}
        }
    }
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
            "period_unit: inch",
            "code_size: x",
            "marker_ids: [-1]",
        ] {
            let e = parse_params(bad).unwrap_err();
            assert!(e.contains("parameter `"), "{bad}: {e}");
        }
    }
}
