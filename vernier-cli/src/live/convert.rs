//! OpenCV frames to [`GreyImage`]: 8/16-bit mono and 8-bit BGR/BGRA frames are read in place
//! (the frame's buffer is borrowed and converted straight to the detector's `f32` grey, no
//! intermediate copy); 16-bit colour is first turned grey by OpenCV (Rec. 601 weights, the
//! same as the library's), because `GreyImage::from_raw` has no 16-bit colour layout.

use opencv::core::{self, Mat, ToInputArray};
use opencv::imgproc;
use opencv::prelude::*;
use vernier::{GreyImage, PixelFormat};

/// The grey image of a frame (or of a region of one); the error names a pixel type the
/// detector cannot read.
pub fn grey_image<M: MatTraitConst + ToInputArray>(mat: &M) -> Result<GreyImage, String> {
    let format = match (mat.depth(), mat.channels()) {
        (core::CV_8U, 1) => PixelFormat::Mono8,
        (core::CV_16U, 1) => PixelFormat::Mono16 {
            big_endian: cfg!(target_endian = "big"),
        },
        (core::CV_8U, 3) => PixelFormat::Bgr8,
        (core::CV_8U, 4) => PixelFormat::Bgra8,
        (core::CV_16U, channels @ (3 | 4)) => return grey_image(&grey16(mat, channels)?),
        (depth, channels) => {
            return Err(format!(
                "frames of {channels} channel(s) of {} cannot be read (8/16-bit mono, BGR \
                 or BGRA only)",
                depth_name(depth)
            ))
        }
    };
    if !mat.is_continuous() {
        // A region of a larger buffer: its rows do not fill the borrowed slice exactly.
        let copy = mat.try_clone().map_err(opencv_error)?;
        return grey_image(&copy);
    }
    let (width, height) = (size(mat.cols())?, size(mat.rows())?);
    let step = mat.mat_step().first().copied().unwrap_or(0);
    let data = mat.data_bytes().map_err(opencv_error)?;
    GreyImage::from_raw(width, height, step, format, data).map_err(|e| e.to_string())
}

/// The layout of a frame, for the run's summary: `640x480 16-bit mono`.
pub fn describe(mat: &impl MatTraitConst) -> String {
    let layout = match mat.channels() {
        1 => "mono".to_string(),
        3 => "BGR".to_string(),
        4 => "BGRA".to_string(),
        n => format!("{n}-channel"),
    };
    format!(
        "{}x{} {} {layout}",
        mat.cols(),
        mat.rows(),
        depth_name(mat.depth())
    )
}

/// A 16-bit BGR(A) frame as 16-bit grey.
fn grey16(mat: &impl ToInputArray, channels: i32) -> Result<Mat, String> {
    let code = if channels == 4 {
        imgproc::COLOR_BGRA2GRAY
    } else {
        imgproc::COLOR_BGR2GRAY
    };
    let mut grey = Mat::default();
    imgproc::cvt_color(mat, &mut grey, code, 0).map_err(opencv_error)?;
    Ok(grey)
}

/// A frame side as `usize` (OpenCV's are `i32`).
fn size(side: i32) -> Result<usize, String> {
    usize::try_from(side).map_err(|_| format!("a frame side of {side} pixels"))
}

/// OpenCV's name of a depth code.
fn depth_name(depth: i32) -> &'static str {
    match depth {
        core::CV_8U => "8-bit",
        core::CV_8S => "8-bit signed",
        core::CV_16U => "16-bit",
        core::CV_16S => "16-bit signed",
        core::CV_32S => "32-bit integers",
        core::CV_32F => "32-bit floats",
        core::CV_64F => "64-bit floats",
        _ => "unknown depth",
    }
}

/// An OpenCV error as text.
pub fn opencv_error(e: opencv::Error) -> String {
    format!("OpenCV: {}", e.message)
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Scalar, CV_16UC1, CV_16UC3, CV_8UC1, CV_8UC2, CV_8UC3};

    fn filled(rows: i32, cols: i32, typ: i32, value: f64) -> Mat {
        Mat::new_rows_cols_with_default(rows, cols, typ, Scalar::all(value)).unwrap()
    }

    #[test]
    fn mono_and_colour_frames_become_grey() {
        for (typ, value, expected) in [
            (CV_8UC1, 51.0, 0.2),
            (CV_8UC3, 51.0, 0.2),
            (CV_16UC1, 13107.0, 0.2),
            (CV_16UC3, 13107.0, 0.2),
        ] {
            let image = grey_image(&filled(3, 5, typ, value)).unwrap();
            assert_eq!((image.width(), image.height()), (5, 3));
            for &v in image.pixels() {
                assert!((v - expected).abs() < 1e-4, "type {typ}: {v}");
            }
        }
    }

    #[test]
    fn regions_of_larger_frames_are_read() {
        let mut big = filled(6, 8, CV_8UC1, 0.0);
        *big.at_2d_mut::<u8>(2, 3).unwrap() = 255;
        let roi = Mat::roi(&big, core::Rect::new(2, 1, 4, 3)).unwrap();
        let image = grey_image(&roi.try_clone().unwrap()).unwrap();
        assert_eq!(image.get(1, 1), Some(1.0));
        let view = grey_image(&roi).unwrap();
        assert_eq!(view, image);
    }

    #[test]
    fn other_layouts_are_errors() {
        let frame = filled(2, 3, CV_8UC2, 0.0);
        let e = grey_image(&frame).unwrap_err();
        assert!(e.contains("2 channel(s) of 8-bit"), "{e}");
        assert_eq!(describe(&frame), "3x2 8-bit 2-channel");
        assert_eq!(describe(&filled(2, 3, CV_16UC1, 0.0)), "3x2 16-bit mono");
    }
}
