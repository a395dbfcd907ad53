//! Fine geometry of one marker from the phase planes of its window (docs/design.md#hp-fine,
//! redone).
//!
//! The original picks the quadrant from the angle of plane 1 and assumes the window centre lies
//! within half a period of the centre dot (docs/design.md#defect-hp-grouping). Here each pattern
//! axis takes the signed plane whose gradient is closest to the finder direction of that axis; the
//! marker width is measured in whole periods between the finders; and the marker centre is the grid
//! point of the right phase nearest to the coarse centre from the finders, found by rounding the
//! phases there to whole periods — any window placement works as long as the finders locate the
//! centre within half a period.

use super::grouping::FinderTriple;
use super::marker_id::DotGrid;
use crate::grey_image::GreyImage;
use crate::layout::HpCodeLayout;
use crate::phase::{
    fit_dot_field_against, fit_dot_field_tracked, wrap_to_pi, FieldFit, NodeMask, PhasePlane,
    Rival, TiltStart,
};
use nalgebra::{Matrix2, Vector2};
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Largest angle between a pattern axis seen by the finders and the matching phase gradient,
/// radians: a larger one means the window's grid is not this marker's.
const MAX_AXIS_ERROR: f64 = 0.3;
/// Largest relative difference between the grid period and twice the finders' module.
const MAX_PERIOD_ERROR: f64 = 0.25;
/// Largest distance of a finder from where the planes and a whole number of periods between
/// the finders put it (perspective included, [`finder_view`]), periods.
const MAX_LEG_ERROR: f64 = 0.35;
/// Fewest periods between two finders (`W ≥ 17`).
const MIN_LEGS: f64 = 5.0;
/// Largest perspective accepted: `|p₁| + |p₂|` times the half-width of the marker, the
/// relative change of depth across it (~0.12 for a marker tilted by 25° that fills a
/// 1.5-diagonal focal length camera's view; beyond, the two finder legs' lengths may differ
/// by a third, which also an unrelated triple of finder-like shapes could show).
const MAX_DEPTH_CHANGE: f64 = 0.25;
/// Gauss–Newton iterations of [`tilted_view`] (it converges in 3–4).
const VIEW_ITERATIONS: usize = 10;
/// The tilted view of the finders is taken when it puts them this many times closer to their
/// places than the untilted one, at least ([`finder_view`]): a tilt moves all three finders
/// off the linear grid in its own pattern, which the two projective terms then explain
/// (misfit 0.5 → below 0.04 period on the stress suite's steeply tilted markers), while a
/// finder moved alone by dust leaves most of its misfit (0.10 → 0.09 on stress scene 52634).
const TILT_GAIN: f64 = 0.5;

/// Marker grid measured in a window, in image pixels.
#[derive(Clone, Copy, Debug)]
pub(crate) struct MarkerGrid {
    /// Phase plane along the pattern x axis (gradient pointing to +x), window frame.
    pub plane_x: PhasePlane,
    /// Phase plane along the pattern y axis, window frame.
    pub plane_y: PhasePlane,
    /// Which engine plane (0 or 1) became `plane_x`.
    pub x_from_plane: usize,
    /// Phase of both planes at the marker centre: 0 (a dot) when `W ≡ 1 (mod 4)`, π (the gap
    /// between four dots) when `W ≡ 3 (mod 4)`.
    pub center_phase: f64,
    /// Whole periods between the window centre's node and the marker centre along x and y.
    pub period_shift: (f64, f64),
    /// Measured marker width in half-period cells `W` (odd).
    pub code_size: usize,
    /// Dot positions (image pixels).
    pub dots: DotGrid,
}

impl MarkerGrid {
    /// Orientation of the marker in the image, radians (y down: clockwise positive): the
    /// direction of the pattern x axis, averaged with that of the y axis turned back by a
    /// quarter turn (`mirrored`: forward), so that a slightly sheared grid (perspective)
    /// gives the same angle whichever axis is called x.
    pub fn alpha(&self, mirrored: bool) -> f64 {
        let quarter = if mirrored { -FRAC_PI_2 } else { FRAC_PI_2 };
        let ax = self.plane_x.angle();
        let shear = wrap_to_pi(self.plane_y.angle() - quarter - ax);
        ax + shear / 2.0
    }
}

/// Assigns the window planes to the marker axes seen by `triple`, measures the marker width and
/// locates its centre.
///
/// `window_center` is the image pixel `(col, row)` at the window's centre index (the origin of
/// the planes' frame). `None` when the planes do not match the finders' geometry (direction,
/// period, legs of whole periods).
pub(crate) fn locate(
    planes: &[PhasePlane; 2],
    triple: &FinderTriple,
    window_center: Vector2<f64>,
) -> Option<MarkerGrid> {
    let ex = triple.right - triple.corner;
    let ey = triple.bottom - triple.corner;
    let candidates = [
        (0, planes[0]),
        (0, planes[0].flipped()),
        (1, planes[1]),
        (1, planes[1].flipped()),
    ];
    let error =
        |p: &PhasePlane, axis: &Vector2<f64>| wrap_to_pi(p.angle() - axis.y.atan2(axis.x)).abs();
    let (ix, plane_x) = *candidates
        .iter()
        .min_by(|a, b| error(&a.1, &ex).total_cmp(&error(&b.1, &ex)))?;
    let (_, plane_y) = *candidates
        .iter()
        .filter(|c| c.0 != ix)
        .min_by(|a, b| error(&a.1, &ey).total_cmp(&error(&b.1, &ey)))?;
    if error(&plane_x, &ex) > MAX_AXIS_ERROR || error(&plane_y, &ey) > MAX_AXIS_ERROR {
        log::trace!(
            "grid axes {:.3}, {:.3} rad off the finders'",
            error(&plane_x, &ex),
            error(&plane_y, &ey)
        );
        return None;
    }
    let expected_period = 2.0 * triple.module_px;
    for p in [&plane_x, &plane_y] {
        if (p.pixel_period() / expected_period - 1.0).abs() > MAX_PERIOD_ERROR {
            log::trace!(
                "grid period {:.2} px, finders say {expected_period:.2} px",
                p.pixel_period()
            );
            return None;
        }
    }
    // Gradients as rows: M·d = phase change over the displacement d.
    let m = Matrix2::new(plane_x.a, plane_x.b, plane_y.a, plane_y.b);
    let inverse = m.try_inverse()?;
    // The finders in periods along the window's lattice axes, from the window centre.
    let lattice = |p: Vector2<f64>| m * (p - window_center) / TAU;
    let finders = [
        lattice(triple.corner),
        lattice(triple.right),
        lattice(triple.bottom),
    ];
    let view = finder_view(&finders)?;
    let code_size = 7 + 2 * view.legs as usize;
    // Centre cell (W − 1)/2 lies (W − 1)/4 periods from the corner dot (phase 0).
    let center_phase = if (code_size - 1) % 4 == 0 { 0.0 } else { PI };
    let coarse = inverse * (TAU * view.center);
    let kx = ((plane_x.at(coarse.x, coarse.y) - center_phase) / TAU).round();
    let ky = ((plane_y.at(coarse.x, coarse.y) - center_phase) / TAU).round();
    let offset = inverse
        * Vector2::new(
            TAU * kx + center_phase - plane_x.c,
            TAU * ky + center_phase - plane_y.c,
        );
    Some(MarkerGrid {
        plane_x,
        plane_y,
        x_from_plane: ix,
        center_phase,
        period_shift: (kx, ky),
        code_size,
        dots: DotGrid {
            perspective: view.perspective,
            ..DotGrid::new(
                window_center + offset,
                inverse * Vector2::new(TAU, 0.0),
                inverse * Vector2::new(0.0, TAU),
                code_size.div_ceil(2),
            )
        },
    })
}

impl MarkerGrid {
    /// The grid with its centre moved to the planes' node `shift` whole periods away along
    /// the pattern axes: a renumbering of the nodes, as [`DotGrid::renumbered`] does for a
    /// grid fitted to the dots.
    pub(crate) fn renumbered(&self, shift: Vector2<f64>) -> MarkerGrid {
        let dots = &self.dots;
        MarkerGrid {
            period_shift: (self.period_shift.0 + shift.x, self.period_shift.1 + shift.y),
            dots: DotGrid {
                center: dots.center + dots.step_x * shift.x + dots.step_y * shift.y,
                ..*dots
            },
            ..*self
        }
    }
}

/// Where the marker's three finders put it on the lattice of the window's planes.
#[derive(Clone, Copy, Debug, PartialEq)]
struct FinderView {
    /// Periods between the corner finder and each of the others, `(W − 7)/2`.
    legs: f64,
    /// Marker centre, periods along the lattice axes from the window centre.
    center: Vector2<f64>,
    /// Perspective `p` per period ([`DotGrid::perspective`]).
    perspective: Vector2<f64>,
    /// Largest distance of a finder from where the view puts it, periods.
    misfit: f64,
}

/// The marker grid refined on its whole dot field (docs/design.md#field-fit), and the fit.
/// `id` is the decoded one: it says which dots exist; the finders are where `grid` says (a
/// mirrored marker's grid reads its layout as from the front). The fit weighs every drawn
/// dot and keeps clear of the finders, the missing ID dots and the marker's edge. `None` when
/// the field is too small, the fit fails or it cannot beat `rival`, the window's fit (the
/// caller keeps the window's grid). With `previous`, the last frame's fit of this marker
/// (tracking), the fit starts from its model ([`fit_dot_field_tracked`]).
pub(crate) fn refine_on_field(
    image: &GreyImage,
    grid: &MarkerGrid,
    id: u64,
    rival: Rival,
    previous: Option<&FieldFit>,
) -> Option<(MarkerGrid, FieldFit)> {
    let dots = &grid.dots;
    let n = dots.size;
    let bitmap = HpCodeLayout::new(1.0, n)
        .ok()?
        .with_id(id)
        .ok()?
        .to_bitmap();
    let last = n as i64 - 1;
    // Nodes (k₁, k₂) = (c, r), dot indices: plane 1 counts columns, plane 2 rows; cell
    // (v₁, v₂) is bitmap cell (row v₂, col v₁). A mirrored marker's grid was located with its
    // right and bottom finders swapped, so its columns run along the marker's own x axis and
    // its layout reads as from the front: the same cells, not their transpose.
    let mask = NodeMask::from_cells(0..=last, 0..=last, |v1, v2| {
        v1 >= 0 && v2 >= 0 && bitmap.cell(v2 as usize, v1 as usize)
    });
    let (cx, cy) = image.center();
    let origin = Vector2::new(cx as f64, cy as f64);
    let to_index = dots.steps().try_inverse()?;
    let h = dots.half_width();
    // φ_x = 2π·c, φ_y = 2π·r at dot (r, c): dot index = h + S⁻¹·(p − centre).
    let plane = |k: usize| {
        let row = to_index.row(k);
        PhasePlane {
            a: TAU * row[0],
            b: TAU * row[1],
            c: TAU * (h + (row * (origin - dots.center))[0]),
        }
    };
    // The marker centre is node (h, h): the fit measures the tilt about it.
    let start = [plane(0), plane(1)];
    let tilt = Some(TiltStart {
        centre: [h, h],
        perspective: dots.perspective,
    });
    let fit = match previous {
        Some(previous) => fit_dot_field_tracked(image, start, &mask, Some(rival), tilt, previous),
        None => fit_dot_field_against(image, start, &mask, Some(rival), tilt),
    }?;
    let [px, py] = fit.planes;
    let gradients = Matrix2::new(px.a, px.b, py.a, py.b);
    let inverse = gradients.try_inverse()?;
    let center = origin + inverse * Vector2::new(TAU * h - px.c, TAU * h - py.c);
    let mut refined = *grid;
    refined.plane_x = PhasePlane {
        a: px.a,
        b: px.b,
        ..grid.plane_x
    };
    refined.plane_y = PhasePlane {
        a: py.a,
        b: py.b,
        ..grid.plane_y
    };
    refined.dots = DotGrid {
        perspective: dots.perspective,
        ..DotGrid::new(
            center,
            inverse * Vector2::new(TAU, 0.0),
            inverse * Vector2::new(0.0, TAU),
            n,
        )
    };
    Some((refined, fit))
}

/// The view of the finders `[corner, right, bottom]` (periods along the lattice axes from the
/// window centre): the whole number of periods `L` between them, the marker centre `c` and
/// the perspective `p` for which `c + u/(1 + p·u)` puts them where they are, `u` their marker
/// coordinates `(∓L/2, ∓L/2)` from the centre. That is the homography of a tilted marker
/// whose steps at the centre are the planes' (measured there): three finders fix its centre
/// and the two projective terms with two equations to spare, which check that the planes
/// belong to these finders.
///
/// `L` is the legs' mean rounded: a tilt stretches one leg and shrinks the other, so their
/// mean stays within a few hundredths of a period of `L` (small, noisy finders let a
/// neighbouring `L` fit with a spurious tilt; it is never tried). The tilted view is taken
/// only when it puts the finders at least [`TILT_GAIN`] times closer to their places than
/// the untilted one (`p = 0`): a finder that dust or blur moves off its place is not a tilt,
/// and a spurious `p` would move the far dots of the grid. `None` when the view leaves a
/// finder more than [`MAX_LEG_ERROR`] from its place.
fn finder_view(finders: &[Vector2<f64>; 3]) -> Option<FinderView> {
    let [corner, right, bottom] = *finders;
    let legs = (0.5 * ((right - corner).x + (bottom - corner).y)).round();
    let flat = untilted_view(finders, legs);
    let tilted = tilted_view(finders, &flat).filter(|t| t.misfit < TILT_GAIN * flat.misfit);
    log::trace!("finders' view: {flat:?}, tilted {tilted:?}");
    match tilted.unwrap_or(flat) {
        v if legs >= MIN_LEGS && v.misfit <= MAX_LEG_ERROR => Some(v),
        _ => {
            log::trace!("finders {finders:?} periods: no view of {legs} periods fits");
            None
        }
    }
}

/// The finders' marker coordinates `u` for `legs` periods between them, periods from the
/// centre.
fn finder_coordinates(legs: f64) -> [Vector2<f64>; 3] {
    let h = legs / 2.0;
    [
        Vector2::new(-h, -h),
        Vector2::new(h, -h),
        Vector2::new(-h, h),
    ]
}

/// Largest distance of `finders` from `places`, periods.
fn misfit(finders: &[Vector2<f64>; 3], places: [Vector2<f64>; 3]) -> f64 {
    (0..3)
        .map(|i| (finders[i] - places[i]).amax())
        .fold(0.0, f64::max)
}

/// [`finder_view`] of an untilted marker (`p = 0`, least squares: the mean offset).
fn untilted_view(finders: &[Vector2<f64>; 3], legs: f64) -> FinderView {
    let u = finder_coordinates(legs);
    let center = (0..3).map(|i| finders[i] - u[i]).sum::<Vector2<f64>>() / 3.0;
    FinderView {
        legs,
        center,
        perspective: Vector2::zeros(),
        misfit: misfit(finders, u.map(|u| center + u)),
    }
}

/// [`finder_view`] of a tilted marker: Gauss–Newton on `(c, p)` from the untilted view `flat`;
/// `None` when singular or beyond [`MAX_DEPTH_CHANGE`].
fn tilted_view(finders: &[Vector2<f64>; 3], flat: &FinderView) -> Option<FinderView> {
    let (legs, start) = (flat.legs, flat.center);
    let u = finder_coordinates(legs);
    // Unknowns (c₁, c₂, p₁, p₂).
    let mut x = nalgebra::Vector4::new(start.x, start.y, 0.0, 0.0);
    let places = |x: &nalgebra::Vector4<f64>| {
        let (c, p) = (Vector2::new(x[0], x[1]), Vector2::new(x[2], x[3]));
        u.map(|u| c + u / (1.0 + p.dot(&u)))
    };
    for _ in 0..VIEW_ITERATIONS {
        let p = Vector2::new(x[2], x[3]);
        let mut jacobian = nalgebra::Matrix6x4::zeros();
        let mut r = nalgebra::Vector6::zeros();
        for (i, place) in places(&x).iter().enumerate() {
            let depth = 1.0 + p.dot(&u[i]);
            for axis in 0..2 {
                let row = 2 * i + axis;
                jacobian[(row, axis)] = 1.0;
                jacobian[(row, 2)] = -u[i][axis] * u[i].x / (depth * depth);
                jacobian[(row, 3)] = -u[i][axis] * u[i].y / (depth * depth);
                r[row] = finders[i][axis] - place[axis];
            }
        }
        // Least-squares step: the places move by J·δ towards the finders.
        let step = (jacobian.transpose() * jacobian).try_inverse()? * (jacobian.transpose() * r);
        x += step;
        if step.amax() < 1e-9 {
            break;
        }
    }
    let perspective = Vector2::new(x[2], x[3]);
    // The depth change at the marker's corners (two periods beyond its finders' centres).
    let depth_change = perspective.abs().sum() * (legs / 2.0 + 2.0);
    let misfit = misfit(finders, places(&x));
    (depth_change <= MAX_DEPTH_CHANGE && misfit.is_finite()).then_some(FinderView {
        legs,
        center: Vector2::new(x[0], x[1]),
        perspective,
        misfit,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grey_image::Polarity;

    /// Planes of a grid rotated by `alpha`, period 10 px, with a node at window offset `node`,
    /// reported like the engine (directions in [0, π)).
    fn planes(alpha: f64, node: Vector2<f64>) -> [PhasePlane; 2] {
        let k = TAU / 10.0;
        let (s, c) = alpha.sin_cos();
        let px = PhasePlane {
            a: k * c,
            b: k * s,
            c: -k * (c * node.x + s * node.y),
        };
        let py = PhasePlane {
            a: -k * s,
            b: k * c,
            c: -k * (-s * node.x + c * node.y),
        };
        [px.flipped(), py.flipped()]
    }

    fn triple(alpha: f64, center: Vector2<f64>, legs_px: f64) -> FinderTriple {
        let (s, c) = alpha.sin_cos();
        let ux = Vector2::new(c, s) * legs_px / 2.0;
        let uy = Vector2::new(-s, c) * legs_px / 2.0;
        FinderTriple {
            corner: center - ux - uy + Vector2::new(1.5, -2.0),
            right: center + ux - uy,
            bottom: center - ux + uy,
            module_px: 5.0,
            polarity: Polarity::BrightDots,
            misfit: 0.0,
        }
    }

    #[test]
    fn resolves_quadrant_and_period_shift() {
        // Centre dot three periods away from the window centre; W = 33 (legs 13 periods).
        let alpha = 2.5;
        let node = Vector2::new(23.0, -12.0);
        let window_center = Vector2::new(500.0, 400.0);
        let center = window_center + node;
        let t = triple(alpha, center, 130.0);
        let g = locate(&planes(alpha, node), &t, window_center).unwrap();
        assert_eq!(g.code_size, 33);
        assert!(
            (g.dots.center - center).norm() < 1e-9,
            "{:?}",
            g.dots.center
        );
        assert!((g.alpha(false) - alpha).abs() < 1e-12);
        assert!((g.dots.step_x - Vector2::new(alpha.cos(), alpha.sin()) * 10.0).norm() < 1e-9);
        // A grid of the wrong period is refused.
        let mut wrong = t;
        wrong.module_px = 8.0;
        assert!(locate(&planes(alpha, node), &wrong, window_center).is_none());
    }

    #[test]
    fn tilted_marker_finders_give_its_perspective() {
        // W = 37 (legs of 15 periods), the centre a node, seen under a homography whose depth
        // changes by 8 % across the marker: the legs are 14.7 and 15.6 periods on the planes'
        // linear grid, with cross terms of 0.54 and 0.36 period, beyond what rounding accepts.
        let alpha: f64 = 0.4;
        let window_center = Vector2::new(300.0, 200.0);
        let node = Vector2::new(3.0, -4.0);
        let center = window_center + node;
        let p = Vector2::new(0.005, -0.003);
        let (s, c) = alpha.sin_cos();
        let steps = Matrix2::new(c, -s, s, c) * 10.0;
        let seen = |u: Vector2<f64>| center + steps * u / (1.0 + p.dot(&u));
        let t = FinderTriple {
            corner: seen(Vector2::new(-7.5, -7.5)),
            right: seen(Vector2::new(7.5, -7.5)),
            bottom: seen(Vector2::new(-7.5, 7.5)),
            module_px: 5.0,
            polarity: Polarity::BrightDots,
            misfit: 0.0,
        };
        let g = locate(&planes(alpha, node), &t, window_center).unwrap();
        assert_eq!(g.code_size, 37);
        assert!((g.dots.center - center).norm() < 1e-9);
        assert!(
            (g.dots.perspective - p).norm() < 1e-9,
            "{:?}",
            g.dots.perspective
        );
        // The ID row's dots are where the homography puts them.
        let corner_dot = g.dots.at(0.0, 18.0);
        assert!((corner_dot - seen(Vector2::new(9.0, -9.0))).norm() < 1e-6);
        // Finders whose legs differ by a third are not one marker, whatever the tilt.
        let mut stretched = t;
        stretched.bottom = t.corner + (t.bottom - t.corner) * 4.0 / 3.0;
        assert!(locate(&planes(alpha, node), &stretched, window_center).is_none());
    }

    #[test]
    fn centre_between_dots_for_w_3_mod_4() {
        // W = 39: legs of 16 periods, centre half a period off the nodes along both axes.
        let alpha = -0.7;
        let node = Vector2::new(4.0, 2.0);
        let window_center = Vector2::new(300.0, 200.0);
        let (s, c) = f64::sin_cos(alpha);
        let center = window_center + node + (Vector2::new(c, s) + Vector2::new(-s, c)) * 5.0;
        let t = triple(alpha, center, 160.0);
        let g = locate(&planes(alpha, node), &t, window_center).unwrap();
        assert_eq!(g.code_size, 39);
        assert!((g.dots.center - center).norm() < 1e-9);
    }
}
