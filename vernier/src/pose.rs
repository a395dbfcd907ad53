//! Poses and frames (docs/design.md#frames).
//!
//! * **Camera frame**: origin at the image centre pixel `(C div 2, R div 2)`, `x_c` right
//!   (columns), `y_c` down (rows), `z_c` into the scene; lengths in pattern units (µm by
//!   convention), a pixel being `pixel_size` pattern units (orthographic microscope model).
//! * **Pattern frame**: `x_p` along increasing layout column, `y_p` along increasing layout row,
//!   origin per layout class (see [`crate::layout`]).
//! * **Transform** `cTp = Trans(0,0,z)·Rz(α)·Ry(β)·Rx(γ)·Trans(x,y,0)`: `(x, y)` are expressed
//!   in the pattern frame, so the image centre sees the pattern point `(−x, −y)` (planar case)
//!   and the pattern origin appears at pixel `centre + Rz(α)·(x, y)/pixel_size`.
//!
//! ROS users want SI units: [`Pose::scaled`] converts lengths (e.g. µm → m with `1e-6`).

use nalgebra::{Isometry3, Point2, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

/// Pose of a pattern in the camera frame (docs/design.md#frames).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pose {
    /// Translation along `x_p`, pattern units (see module docs for its meaning).
    pub x: f64,
    /// Translation along `y_p`, pattern units.
    pub y: f64,
    /// Distance along the camera axis, pattern units (0 for planar poses).
    pub z: f64,
    /// Rotation about the camera z axis, radians, in `[−π, π)`; positive turns `x_c` towards
    /// `y_c` (clockwise on screen).
    pub alpha: f64,
    /// Rotation about the intrinsic y axis, radians (out of plane; 0 for planar poses).
    pub beta: f64,
    /// Rotation about the intrinsic x axis, radians (out of plane; 0 for planar poses).
    pub gamma: f64,
    /// Pattern units per image pixel.
    pub pixel_size: f64,
}

impl Pose {
    /// In-plane pose: `(x, y)` pattern units, `alpha` radians (wrapped to `[−π, π)`),
    /// `pixel_size` pattern units per pixel.
    pub fn planar(x: f64, y: f64, alpha: f64, pixel_size: f64) -> Self {
        Pose {
            x,
            y,
            z: 0.0,
            alpha: crate::phase::wrap_angle(alpha),
            beta: 0.0,
            gamma: 0.0,
            pixel_size,
        }
    }

    /// The planar pose whose pattern origin appears at `origin_px` (pixels, camera frame: relative
    /// to the image centre pixel, y down) with orientation `alpha`:
    /// `(x, y) = Rz(−α)·origin_px·pixel_size`.
    pub fn from_origin_in_image(origin_px: Vector2<f64>, alpha: f64, pixel_size: f64) -> Self {
        let p = rotate2(origin_px * pixel_size, -alpha);
        Pose::planar(p.x, p.y, alpha, pixel_size)
    }

    /// Rotation part of `cTp`: `Rz(α)·Ry(β)·Rx(γ)`.
    pub fn rotation(&self) -> Rotation3<f64> {
        Rotation3::from_axis_angle(&Vector3::z_axis(), self.alpha)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), self.beta)
            * Rotation3::from_axis_angle(&Vector3::x_axis(), self.gamma)
    }

    /// `cTp`: maps pattern-frame points to camera-frame points (pattern units).
    pub fn camera_from_pattern(&self) -> Isometry3<f64> {
        let rotation = self.rotation();
        let translation =
            Vector3::new(0.0, 0.0, self.z) + rotation * Vector3::new(self.x, self.y, 0.0);
        Isometry3::from_parts(
            Translation3::from(translation),
            UnitQuaternion::from_rotation_matrix(&rotation),
        )
    }

    /// `pTc`, the inverse of [`Pose::camera_from_pattern`].
    pub fn pattern_from_camera(&self) -> Isometry3<f64> {
        self.camera_from_pattern().inverse()
    }

    /// Position of the pattern origin in the image, pixels relative to the image centre pixel
    /// (orthographic projection).
    pub fn origin_in_image(&self) -> Vector2<f64> {
        let t = self.camera_from_pattern().translation.vector;
        Vector2::new(t.x, t.y) / self.pixel_size
    }

    /// Pixel coordinates `(col, row)` of the pattern point `p` (pattern units), for an image
    /// whose centre pixel is `center` (orthographic projection).
    pub fn project(&self, p: Point2<f64>, center: Point2<f64>) -> Point2<f64> {
        let c = self.camera_from_pattern() * nalgebra::Point3::new(p.x, p.y, 0.0);
        Point2::new(
            center.x + c.x / self.pixel_size,
            center.y + c.y / self.pixel_size,
        )
    }

    /// The same pose with lengths multiplied by `factor` (`x, y, z, pixel_size`), e.g. `1e-6` to
    /// go from µm to metres.
    pub fn scaled(&self, factor: f64) -> Pose {
        Pose {
            x: self.x * factor,
            y: self.y * factor,
            z: self.z * factor,
            pixel_size: self.pixel_size * factor,
            ..*self
        }
    }

    /// The same pose seen with a pixel size of `pixel_size` (pattern units per pixel) instead
    /// of `self.pixel_size`: the pattern origin stays where the image shows it (same
    /// [`Pose::origin_in_image`], pixels) and the rotation is kept, so the translation scales
    /// by `pixel_size / self.pixel_size` (docs/design.md#calibrated-scale). Unchanged when
    /// `self.pixel_size` is not positive.
    pub fn with_pixel_size(&self, pixel_size: f64) -> Pose {
        if self.pixel_size.is_nan() || self.pixel_size <= 0.0 {
            return *self;
        }
        let ratio = pixel_size / self.pixel_size;
        // t = (0, 0, z) + R·(x, y, 0): its image-plane part is linear in (x, y).
        Pose {
            x: self.x * ratio,
            y: self.y * ratio,
            pixel_size,
            ..*self
        }
    }

    /// `aTb`: the pose of `other`'s pattern frame expressed in this pose's pattern frame
    /// (both measured in the same camera frame). This is what a flexure force sensor reads.
    pub fn relative(&self, other: &Pose) -> Isometry3<f64> {
        self.pattern_from_camera() * other.camera_from_pattern()
    }

    /// OpenCV-style `(rvec, tvec)`: Rodrigues vector of the rotation of `cTp` and its
    /// translation (pattern units).
    pub fn rvec_tvec(&self) -> (Vector3<f64>, Vector3<f64>) {
        let iso = self.camera_from_pattern();
        (iso.rotation.scaled_axis(), iso.translation.vector)
    }
}

/// Rotates a 2-D vector by `angle` radians (`Rz` restricted to the plane).
pub fn rotate2(v: Vector2<f64>, angle: f64) -> Vector2<f64> {
    let (s, c) = angle.sin_cos();
    Vector2::new(c * v.x - s * v.y, s * v.x + c * v.y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_original_regression_values() {
        let pose = Pose {
            x: -2.0,
            y: -3.0,
            z: 5.0,
            alpha: 0.2,
            beta: -0.3,
            gamma: 0.4,
            pixel_size: 1.0,
        };
        let m = pose.camera_from_pattern().to_homogeneous();
        let row0 = [
            0.936293363584199,
            -0.295773602360636,
            -0.189400933088512,
            -0.985265920086491,
        ];
        let row2 = [
            0.295520206661340,
            0.372025551942260,
            0.879923176281257,
            3.292882930850542,
        ];
        for j in 0..4 {
            assert!(
                (m[(0, j)] - row0[j]).abs() < 1e-12,
                "row 0 col {j}: {}",
                m[(0, j)]
            );
            assert!(
                (m[(2, j)] - row2[j]).abs() < 1e-12,
                "row 2 col {j}: {}",
                m[(2, j)]
            );
        }
        let (rvec, tvec) = Pose::planar(3.0, 5.0, 0.2, 1.0).rvec_tvec();
        assert!((rvec - Vector3::new(0.0, 0.0, 0.2)).norm() < 1e-12);
        assert!((tvec - Vector3::new(1.946853, 5.496341, 0.0)).norm() < 1e-6);
    }

    #[test]
    fn origin_round_trip_and_relative() {
        let pose = Pose::from_origin_in_image(Vector2::new(12.0, -7.0), 0.7, 2.0);
        assert!((pose.origin_in_image() - Vector2::new(12.0, -7.0)).norm() < 1e-12);
        let other = Pose::planar(pose.x + 3.0, pose.y, 0.7, 2.0);
        let rel = pose.relative(&other);
        assert!((rel.translation.vector - Vector3::new(3.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(rel.rotation.angle() < 1e-12);
    }

    #[test]
    fn a_calibrated_pixel_size_keeps_the_origin_in_the_image() {
        let mut pose = Pose::from_origin_in_image(Vector2::new(480.0, -130.0), 0.3, 0.50001);
        pose.beta = 0.1;
        pose.gamma = -0.2;
        let calibrated = pose.with_pixel_size(0.5);
        let moved = calibrated.origin_in_image() - pose.origin_in_image();
        assert!(moved.norm() < 1e-9, "{moved}");
        assert_eq!(calibrated.pixel_size, 0.5);
        assert_eq!(
            (calibrated.alpha, calibrated.beta, calibrated.gamma),
            (0.3, 0.1, -0.2)
        );
        // 480 px from the centre, a 2e-5 scale error is 1e-2 px of position.
        let shift = Vector2::new(pose.x - calibrated.x, pose.y - calibrated.y).norm() / 0.5;
        assert!((shift - 2e-5 * 497.3).abs() < 0.05 * shift, "{shift}");
    }
}
