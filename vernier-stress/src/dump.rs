//! Writing a scene for inspection: the image as a 16-bit PNG and a JSON file with the spec,
//! degradations, truth, detections and verdicts.

use crate::error::Result;
use crate::evaluate::Verdict;
use crate::suite::Outcome;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// JSON description of an outcome (what the dump writes beside the image).
pub fn outcome_json(o: &Outcome) -> Value {
    let s = &o.scene;
    let truth: Vec<Value> = s
        .truth
        .iter()
        .map(|t| {
            json!({
                "family": t.family.name(),
                "code_size": t.code_size,
                "id": t.id,
                "origin_px": t.origin_px,
                "angle": t.angle,
                "pixel_size": t.pixel_size,
                "period_px": t.period_px,
                "mirrored": t.mirrored,
                "expectation": t.expectation.name(),
            })
        })
        .collect();
    let detections: Vec<Value> = o
        .detections
        .iter()
        .zip(&o.result.verdicts)
        .map(|(d, v)| {
            let verdict = match v {
                Verdict::Found {
                    truth,
                    position_error,
                    angle_error,
                    predicted_std_px,
                } => json!({
                    "found": truth,
                    "position_error_px": position_error,
                    "angle_error_rad": angle_error,
                    "predicted_std_px": predicted_std_px,
                }),
                Verdict::WrongId { truth } => json!({"wrong_id": truth}),
                Verdict::Ignored { truth } => json!({"ignored": truth}),
                Verdict::False => json!("false"),
            };
            json!({
                "id": d.id,
                "origin_px": [d.origin_px.x, d.origin_px.y],
                "alpha": d.pose.alpha,
                "pixel_size": d.pose.pixel_size,
                "quality": d.quality,
                "decode_confidence": d.decode_confidence,
                "verdict": verdict,
            })
        })
        .collect();
    json!({
        "seed": s.spec.seed,
        "family": s.spec.family.name(),
        "category": s.spec.category.name(),
        "size": [s.image.width(), s.image.height()],
        "polarity": format!("{:?}", s.polarity),
        "code_size": s.code_size,
        "degradations": s.degradations.describe(),
        "notes": s.notes,
        "generation_ms": s.timings.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<serde_json::Map<String, Value>>(),
        "truth": truth,
        "detections": detections,
        "result": {
            "markers": o.result.markers,
            "found": o.result.found,
            "wrong_id": o.result.wrong_id,
            "false_markers": o.result.false_markers,
            "missed": o.result.missed,
            "error": o.result.error,
            "detect_ms": o.result.detect_ms,
        },
    })
}

/// Writes `scene_<seed>.png` (16-bit grey) and `scene_<seed>.json` into `dir` (created if
/// needed); returns the PNG path.
pub fn dump(dir: &Path, o: &Outcome) -> Result<PathBuf> {
    std::fs::create_dir_all(dir)?;
    let seed = o.scene.spec.seed;
    let png = dir.join(format!("scene_{seed}.png"));
    o.scene.image.save_png(&png, 16)?;
    let text = serde_json::to_string_pretty(&outcome_json(o))?;
    std::fs::write(dir.join(format!("scene_{seed}.json")), text + "\n")?;
    Ok(png)
}
