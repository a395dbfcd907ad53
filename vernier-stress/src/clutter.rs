//! Clutter drawn beside the markers (never over them): text-like glyph blocks, stripes and
//! grid paper. Other markers used as clutter are ordinary [`crate::markers::Placed`] markers.

use crate::geometry::{rotate, OrientedRect};
use crate::raster::Plane;
use nalgebra::Vector2;
use rand::rngs::SmallRng;
use rand::Rng;

/// Glyph strokes in a 4 × 6 unit box (x right, y down).
const GLYPHS: [&[[f64; 4]]; 18] = [
    &[[0., 6., 2., 0.], [2., 0., 4., 6.], [1., 3.5, 3., 3.5]], // A
    &[
        [0., 0., 0., 6.],
        [0., 0., 4., 0.],
        [0., 3., 3., 3.],
        [0., 6., 4., 6.],
    ], // E
    &[[0., 0., 0., 6.], [0., 0., 4., 0.], [0., 3., 3., 3.]],   // F
    &[[0., 0., 0., 6.], [4., 0., 4., 6.], [0., 3., 4., 3.]],   // H
    &[[2., 0., 2., 6.], [1., 0., 3., 0.], [1., 6., 3., 6.]],   // I
    &[[0., 0., 0., 6.], [4., 0., 0., 3.5], [1.3, 2.7, 4., 6.]], // K
    &[[0., 0., 0., 6.], [0., 6., 4., 6.]],                     // L
    &[
        [0., 6., 0., 0.],
        [0., 0., 2., 3.],
        [2., 3., 4., 0.],
        [4., 0., 4., 6.],
    ], // M
    &[[0., 6., 0., 0.], [0., 0., 4., 6.], [4., 6., 4., 0.]],   // N
    &[
        [0., 0., 4., 0.],
        [4., 0., 4., 6.],
        [4., 6., 0., 6.],
        [0., 6., 0., 0.],
    ], // O
    &[[0., 0., 4., 0.], [2., 0., 2., 6.]],                     // T
    &[[0., 0., 2., 6.], [2., 6., 4., 0.]],                     // V
    &[[0., 0., 4., 6.], [4., 0., 0., 6.]],                     // X
    &[[0., 0., 4., 0.], [4., 0., 0., 6.], [0., 6., 4., 6.]],   // Z
    &[[1., 1., 2., 0.], [2., 0., 2., 6.], [1., 6., 3., 6.]],   // 1
    &[[0., 0., 4., 0.], [4., 0., 1.5, 6.]],                    // 7
    &[[0., 0., 0., 6.], [0., 6., 4., 6.], [4., 6., 4., 0.]],   // U
    &[
        [0., 6., 0., 0.],
        [0., 0., 4., 0.],
        [4., 0., 4., 3.],
        [4., 3., 0., 3.],
    ], // P
];

/// One clutter item.
#[derive(Clone, Debug, PartialEq)]
pub enum Clutter {
    /// Lines of stroked glyphs.
    Text {
        /// Outline of the block.
        rect: OrientedRect,
        /// Glyph index per character (`None` = space), per line.
        lines: Vec<Vec<Option<usize>>>,
        /// Pixels per glyph unit (glyph height = 6 units).
        unit: f64,
        /// Stroke half width, pixels.
        half_stroke: f64,
        /// Coverage value of the strokes.
        value: f32,
    },
    /// Parallel bars across the block (along its y axis), period `period` pixels.
    Stripes {
        /// Outline.
        rect: OrientedRect,
        /// Stripe period, pixels.
        period: f64,
        /// Bar width over period.
        duty: f64,
        /// Coverage value of the bars.
        value: f32,
    },
    /// Grid-paper lines both ways, `spacing` pixels apart.
    Grid {
        /// Outline.
        rect: OrientedRect,
        /// Line spacing, pixels.
        spacing: f64,
        /// Line half width, pixels.
        half_width: f64,
        /// Coverage value of the lines.
        value: f32,
    },
}

fn block_angle(rng: &mut SmallRng) -> f64 {
    if rng.random_bool(0.6) {
        rng.random_range(0..4) as f64 * std::f64::consts::FRAC_PI_2 + rng.random_range(-0.05..0.05)
    } else {
        rng.random_range(-std::f64::consts::PI..std::f64::consts::PI)
    }
}

impl Clutter {
    /// A random item of a random kind centred on `center` (its size drawn here).
    pub fn random(rng: &mut SmallRng, center: Vector2<f64>) -> Clutter {
        let angle = block_angle(rng);
        let value = rng.random_range(0.4..1.0f32);
        match rng.random_range(0..3) {
            0 => {
                let height_px: f64 = rng.random_range(8.0..40.0);
                let unit = height_px / 6.0;
                let n_lines = rng.random_range(1..=3usize);
                let n_chars = rng.random_range(2..=12usize);
                let lines = (0..n_lines)
                    .map(|_| {
                        (0..n_chars)
                            .map(|_| {
                                (!rng.random_bool(0.12)).then(|| rng.random_range(0..GLYPHS.len()))
                            })
                            .collect()
                    })
                    .collect();
                let half_stroke = (unit * rng.random_range(0.35..0.8)).max(0.6);
                let size = Vector2::new(
                    (n_chars as f64 * 5.0 - 1.0) * unit,
                    (n_lines as f64 * 9.0 - 3.0) * unit,
                ) + Vector2::repeat(2.0 * half_stroke);
                Clutter::Text {
                    rect: OrientedRect {
                        center,
                        half: size / 2.0,
                        angle,
                    },
                    lines,
                    unit,
                    half_stroke,
                    value,
                }
            }
            1 => Clutter::Stripes {
                rect: OrientedRect {
                    center,
                    half: Vector2::new(
                        rng.random_range(15.0..150.0),
                        rng.random_range(15.0..150.0),
                    ),
                    angle,
                },
                period: (rng.random_range(3f64.ln()..50f64.ln())).exp(),
                duty: rng.random_range(0.3..0.7),
                value,
            },
            _ => Clutter::Grid {
                rect: OrientedRect {
                    center,
                    half: Vector2::new(
                        rng.random_range(40.0..250.0),
                        rng.random_range(40.0..250.0),
                    ),
                    angle,
                },
                spacing: (rng.random_range(8f64.ln()..60f64.ln())).exp(),
                half_width: rng.random_range(0.5..1.0),
                value: value * 0.7,
            },
        }
    }

    /// Outline of the item.
    pub fn footprint(&self) -> OrientedRect {
        match self {
            Clutter::Text { rect, .. }
            | Clutter::Stripes { rect, .. }
            | Clutter::Grid { rect, .. } => *rect,
        }
    }

    /// Short name for reports.
    pub fn name(&self) -> &'static str {
        match self {
            Clutter::Text { .. } => "text",
            Clutter::Stripes { .. } => "stripes",
            Clutter::Grid { .. } => "grid",
        }
    }

    /// Paints the item into `plane` (coverage, max-composited).
    pub fn paint(&self, plane: &mut Plane) {
        match self {
            Clutter::Text {
                rect,
                lines,
                unit,
                half_stroke,
                value,
            } => {
                let origin = -rect.half + Vector2::repeat(*half_stroke);
                for (li, line) in lines.iter().enumerate() {
                    for (ci, glyph) in line.iter().enumerate() {
                        let Some(g) = glyph.and_then(|g| GLYPHS.get(g)) else {
                            continue;
                        };
                        let base = origin + Vector2::new(ci as f64 * 5.0, li as f64 * 9.0) * *unit;
                        for s in g.iter() {
                            let to_image = |x: f64, y: f64| {
                                rect.center + rotate(base + Vector2::new(x, y) * *unit, rect.angle)
                            };
                            plane.draw_segment(
                                to_image(s[0], s[1]),
                                to_image(s[2], s[3]),
                                *half_stroke,
                                *value,
                            );
                        }
                    }
                }
            }
            Clutter::Stripes {
                rect,
                period,
                duty,
                value,
            } => {
                let (half, p, duty, v) = (rect.half, *period, *duty, *value);
                plane.paint_rect(rect, &mut |l| {
                    if l.x.abs() > half.x || l.y.abs() > half.y {
                        return 0.0;
                    }
                    let phase = ((l.x + half.x) / p).fract();
                    let d = (phase - 0.5).abs() * p;
                    v * (duty * p / 2.0 - d + 0.5).clamp(0.0, 1.0) as f32
                });
            }
            Clutter::Grid {
                rect,
                spacing,
                half_width,
                value,
            } => {
                let (half, s, hw, v) = (rect.half, *spacing, *half_width, *value);
                plane.paint_rect(rect, &mut |l| {
                    if l.x.abs() > half.x || l.y.abs() > half.y {
                        return 0.0;
                    }
                    let line = |t: f64| {
                        let f = (t / s).rem_euclid(1.0);
                        let d = f.min(1.0 - f) * s;
                        (hw + 0.5 - d).clamp(0.0, 1.0)
                    };
                    v * line(l.x + half.x).max(line(l.y + half.y)) as f32
                });
            }
        }
    }
}
