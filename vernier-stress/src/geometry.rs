//! Plane geometry of a scene: the tilt homography (marker plane → image) and oriented
//! rectangles (footprints of markers and clutter, overlap tests).

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

/// A projective map from the marker plane to the image, both in pixel coordinates
/// `(col, row)`. The identity for scenes without perspective.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Homography {
    forward: Matrix3<f64>,
    inverse: Matrix3<f64>,
}

impl Homography {
    /// The identity map.
    pub fn identity() -> Self {
        Homography {
            forward: Matrix3::identity(),
            inverse: Matrix3::identity(),
        }
    }

    /// A pinhole camera of focal length `focal` pixels looking at the plane rotated by `tilt`
    /// radians about the in-plane axis of direction `axis_angle` through `center`. The
    /// centre maps to itself with unit scale along the tilt axis (foreshortening `cos tilt`
    /// across it). `None` when the plane would be seen edge-on (`|tilt| ≥ π/2`) or `focal`
    /// is not positive.
    pub fn tilt(center: Vector2<f64>, tilt: f64, axis_angle: f64, focal: f64) -> Option<Self> {
        if !(tilt.abs() < std::f64::consts::FRAC_PI_2 && focal.is_finite() && focal > 0.0) {
            return None;
        }
        let axis = Vector3::new(axis_angle.cos(), axis_angle.sin(), 0.0);
        let r = nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), tilt);
        let r = r.matrix();
        // [r1 r2 t] with t = (0, 0, f): plane point (u, v) ↦ R·(u, v, 0) + (0, 0, f).
        let rt = Matrix3::new(
            r[(0, 0)],
            r[(0, 1)],
            0.0,
            r[(1, 0)],
            r[(1, 1)],
            0.0,
            r[(2, 0)],
            r[(2, 1)],
            focal,
        );
        let k = Matrix3::new(focal, 0.0, 0.0, 0.0, focal, 0.0, 0.0, 0.0, 1.0);
        let shift = |d: Vector2<f64>| Matrix3::new(1.0, 0.0, d.x, 0.0, 1.0, d.y, 0.0, 0.0, 1.0);
        let forward = shift(center) * k * rt * shift(-center);
        let inverse = forward.try_inverse()?;
        Some(Homography { forward, inverse })
    }

    /// The map `p ↦ forward·(p, 1)` (homogeneous, row-major 3×3); `None` when singular.
    pub fn from_matrix(forward: Matrix3<f64>) -> Option<Self> {
        let inverse = forward.try_inverse()?;
        Some(Homography { forward, inverse })
    }

    /// The forward map's matrix ([`Homography::from_matrix`]).
    pub fn matrix(&self) -> Matrix3<f64> {
        self.forward
    }

    /// True for the identity map.
    pub fn is_identity(&self) -> bool {
        self.forward == Matrix3::identity()
    }

    fn map(m: &Matrix3<f64>, p: Vector2<f64>) -> Option<Vector2<f64>> {
        let q = m * Vector3::new(p.x, p.y, 1.0);
        (q.z > 1e-9).then(|| Vector2::new(q.x / q.z, q.y / q.z))
    }

    /// Image of the plane point `p`; `None` at or behind the horizon.
    pub fn apply(&self, p: Vector2<f64>) -> Option<Vector2<f64>> {
        Self::map(&self.forward, p)
    }

    /// Plane point seen at image point `q`; `None` beyond the horizon.
    pub fn apply_inverse(&self, q: Vector2<f64>) -> Option<Vector2<f64>> {
        Self::map(&self.inverse, q)
    }

    /// The inverse map as a row-major 3×3 matrix (for fast per-pixel use).
    pub fn inverse_matrix(&self) -> [[f64; 3]; 3] {
        let m = &self.inverse;
        [
            [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
            [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
            [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
        ]
    }

    /// Jacobian `∂(image)/∂(plane)` at plane point `p` (central differences of the exact map).
    pub fn jacobian(&self, p: Vector2<f64>) -> Option<Matrix2<f64>> {
        let h = 1e-3;
        let dx = (self.apply(p + Vector2::new(h, 0.0))? - self.apply(p - Vector2::new(h, 0.0))?)
            / (2.0 * h);
        let dy = (self.apply(p + Vector2::new(0.0, h))? - self.apply(p - Vector2::new(0.0, h))?)
            / (2.0 * h);
        Some(Matrix2::new(dx.x, dy.x, dx.y, dy.y))
    }
}

/// Rotates `v` by `angle` radians (clockwise on screen, y down).
pub fn rotate(v: Vector2<f64>, angle: f64) -> Vector2<f64> {
    let (s, c) = angle.sin_cos();
    Vector2::new(c * v.x - s * v.y, s * v.x + c * v.y)
}

/// A rectangle of half sides `half` along its own axes, turned by `angle` about `center`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrientedRect {
    /// Centre, pixels.
    pub center: Vector2<f64>,
    /// Half sides along the rectangle's own x and y axes, pixels.
    pub half: Vector2<f64>,
    /// Direction of the rectangle's x axis, radians.
    pub angle: f64,
}

impl OrientedRect {
    /// A square of side `side` turned by `angle` about `center`.
    pub fn square(center: Vector2<f64>, side: f64, angle: f64) -> Self {
        OrientedRect {
            center,
            half: Vector2::new(side / 2.0, side / 2.0),
            angle,
        }
    }

    /// The same rectangle with every side moved out by `margin`.
    pub fn expanded(&self, margin: f64) -> Self {
        OrientedRect {
            half: self.half + Vector2::new(margin, margin),
            ..*self
        }
    }

    /// The four corners, in order around the rectangle.
    pub fn corners(&self) -> [Vector2<f64>; 4] {
        [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(sx, sy)| {
            self.center + rotate(Vector2::new(sx * self.half.x, sy * self.half.y), self.angle)
        })
    }

    /// Half extents of the axis-aligned bounding box.
    pub fn bounding_half(&self) -> Vector2<f64> {
        let (s, c) = self.angle.sin_cos();
        Vector2::new(
            c.abs() * self.half.x + s.abs() * self.half.y,
            s.abs() * self.half.x + c.abs() * self.half.y,
        )
    }

    /// `p` in the rectangle's own frame (origin at the centre, axes along its sides).
    pub fn local(&self, p: Vector2<f64>) -> Vector2<f64> {
        rotate(p - self.center, -self.angle)
    }

    /// True when `p` lies inside (or on the boundary).
    pub fn contains(&self, p: Vector2<f64>) -> bool {
        let l = self.local(p);
        l.x.abs() <= self.half.x && l.y.abs() <= self.half.y
    }

    /// True when the two rectangles share any point (separating-axis test).
    pub fn overlaps(&self, other: &OrientedRect) -> bool {
        let axes = [
            rotate(Vector2::x(), self.angle),
            rotate(Vector2::y(), self.angle),
            rotate(Vector2::x(), other.angle),
            rotate(Vector2::y(), other.angle),
        ];
        let (a, b) = (self.corners(), other.corners());
        axes.iter().all(|axis| {
            let range = |pts: &[Vector2<f64>; 4]| {
                pts.iter()
                    .map(|p| p.dot(axis))
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                        (lo.min(v), hi.max(v))
                    })
            };
            let (alo, ahi) = range(&a);
            let (blo, bhi) = range(&b);
            ahi >= blo && bhi >= alo
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tilt_fixes_the_centre_and_inverts() {
        let c = Vector2::new(320.0, 240.0);
        let h = Homography::tilt(c, 0.4, 0.7, 1500.0).expect("valid tilt");
        let q = h.apply(c).expect("in front");
        assert!((q - c).norm() < 1e-9);
        let p = Vector2::new(17.0, 403.0);
        let back = h.apply_inverse(h.apply(p).expect("fwd")).expect("inv");
        assert!((back - p).norm() < 1e-9);
        let j = h.jacobian(c).expect("jacobian");
        assert!((j.determinant() - 0.4f64.cos()).abs() < 1e-6);
        assert!(Homography::identity().is_identity());
    }

    #[test]
    fn oriented_rect_overlap() {
        let a = OrientedRect::square(Vector2::new(0.0, 0.0), 10.0, 0.0);
        let b = OrientedRect::square(Vector2::new(12.0, 0.0), 10.0, 0.0);
        assert!(!a.overlaps(&b));
        assert!(a.expanded(2.5).overlaps(&b) && !a.expanded(1.5).overlaps(&b));
        // A diamond whose corner pokes into the square.
        let d = OrientedRect::square(Vector2::new(11.0, 0.0), 10.0, std::f64::consts::FRAC_PI_4);
        assert!(a.overlaps(&d));
        let far = OrientedRect::square(Vector2::new(13.0, 0.0), 10.0, std::f64::consts::FRAC_PI_4);
        assert!(!a.overlaps(&far));
        assert!(a.contains(Vector2::new(4.9, -4.9)));
        let h = d.bounding_half();
        assert!((h.x - 50f64.sqrt()).abs() < 1e-9);
    }
}
