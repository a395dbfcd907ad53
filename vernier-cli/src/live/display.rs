//! `vernier live --display`: a preview window (OpenCV highgui) with each marker's origin, ID
//! and pattern axes drawn over the frame.

use opencv::core::{self, Mat, Point, Scalar};
use opencv::highgui;
use opencv::imgproc;
use opencv::prelude::*;
use vernier::MarkerPose;

use super::convert::opencv_error;

/// The window's title.
const WINDOW: &str = "vernier live";
/// Axis arrows, as a fraction of the frame's smaller side (as in the rerun log).
const AXIS_FRACTION: f64 = 0.1;
/// Key codes that close the preview: `q` and Esc.
const QUIT_KEYS: [i32; 2] = [b'q' as i32, 27];

/// An open preview window.
pub struct Preview;

impl Preview {
    /// Opens the window. Fails, instead of letting the GUI toolkit abort the process, when
    /// there is no graphical session to connect to.
    pub fn open() -> Result<Self, String> {
        #[cfg(target_os = "linux")]
        session::check()?;
        highgui::named_window(WINDOW, highgui::WINDOW_NORMAL | highgui::WINDOW_KEEPRATIO)
            .map_err(|e| format!("--display: cannot open a window: {}", e.message))?;
        Ok(Preview)
    }

    /// Shows `frame` with `markers` drawn. Returns false when the user closed the window
    /// (or pressed `q` or Esc).
    pub fn show(&mut self, frame: &Mat, markers: &[MarkerPose]) -> Result<bool, String> {
        let mut canvas = bgr8(frame)?;
        draw_markers(&mut canvas, markers)?;
        highgui::imshow(WINDOW, &canvas).map_err(opencv_error)?;
        let key = highgui::wait_key(1).map_err(opencv_error)?;
        // 0 = closed; backends that cannot tell (GTK) answer -1 or an error: still open.
        let visible = highgui::get_window_property(WINDOW, highgui::WND_PROP_VISIBLE)
            .map_or(true, |v| v != 0.0);
        Ok(visible && !QUIT_KEYS.contains(&(key & 0xff)))
    }
}

/// A fresh 8-bit BGR copy of the frame to draw on (16-bit frames stretched to 0–255).
fn bgr8(frame: &Mat) -> Result<Mat, String> {
    let mut eight = Mat::default();
    if frame.depth() == core::CV_8U {
        eight = frame.try_clone().map_err(opencv_error)?;
    } else {
        core::normalize(
            frame,
            &mut eight,
            0.0,
            255.0,
            core::NORM_MINMAX,
            core::CV_8U,
            &core::no_array(),
        )
        .map_err(opencv_error)?;
    }
    let code = match eight.channels() {
        1 => imgproc::COLOR_GRAY2BGR,
        4 => imgproc::COLOR_BGRA2BGR,
        _ => return Ok(eight),
    };
    let mut bgr = Mat::default();
    imgproc::cvt_color(&eight, &mut bgr, code, 0).map_err(opencv_error)?;
    Ok(bgr)
}

/// Draws each marker: a yellow circle at its origin, its ID, its x axis in red and y axis
/// in green (image y down: x_p → (cos α, sin α), y_p → (−sin α, cos α)).
fn draw_markers(canvas: &mut Mat, markers: &[MarkerPose]) -> Result<(), String> {
    let side = f64::from(canvas.cols().min(canvas.rows()));
    let length = AXIS_FRACTION * side;
    let thickness = ((side / 400.0).round() as i32).max(1);
    let point = |x: f64, y: f64| Point::new(x.round() as i32, y.round() as i32);
    for marker in markers {
        let (x, y) = (marker.origin_px.x, marker.origin_px.y);
        if !(x.is_finite() && y.is_finite()) {
            continue;
        }
        let (s, c) = marker.pose.alpha.sin_cos();
        let origin = point(x, y);
        let axes = [
            (
                point(x + length * c, y + length * s),
                Scalar::new(40.0, 40.0, 255.0, 0.0),
            ),
            (
                point(x - length * s, y + length * c),
                Scalar::new(40.0, 220.0, 40.0, 0.0),
            ),
        ];
        for (tip, colour) in axes {
            imgproc::arrowed_line(
                canvas,
                origin,
                tip,
                colour,
                thickness,
                imgproc::LINE_AA,
                0,
                0.1,
            )
            .map_err(opencv_error)?;
        }
        let yellow = Scalar::new(0.0, 200.0, 255.0, 0.0);
        imgproc::circle(
            canvas,
            origin,
            3 * thickness,
            yellow,
            thickness,
            imgproc::LINE_AA,
            0,
        )
        .map_err(opencv_error)?;
        imgproc::put_text(
            canvas,
            &format!("id {}", marker.id),
            point(
                x + 4.0 * f64::from(thickness),
                y - 4.0 * f64::from(thickness),
            ),
            imgproc::FONT_HERSHEY_SIMPLEX,
            0.5 * f64::from(thickness),
            yellow,
            thickness,
            imgproc::LINE_AA,
            false,
        )
        .map_err(opencv_error)?;
    }
    Ok(())
}

/// Linux: whether a graphical session can be reached, checked before OpenCV's GUI toolkit
/// (Qt in Debian's build) tries and aborts the process when it cannot.
#[cfg(target_os = "linux")]
mod session {
    use std::time::Duration;

    /// How long a remote X server (`ssh -X`: `localhost:10.0`) may take to accept, ms.
    const CONNECT_MS: u64 = 2000;

    /// Ok when the X server of `DISPLAY` accepts a connection, or, without `DISPLAY`, when
    /// the Wayland socket of `WAYLAND_DISPLAY` exists.
    pub fn check() -> Result<(), String> {
        let display = std::env::var("DISPLAY").unwrap_or_default();
        if display.is_empty() {
            return wayland();
        }
        let (host, number) = parse(&display).ok_or_else(|| {
            format!("--display: DISPLAY=`{display}` is not an X display (`:0`, `host:10.0`)")
        })?;
        let reached = match host {
            None => {
                let socket = format!("/tmp/.X11-unix/X{number}");
                std::os::unix::net::UnixStream::connect(socket).is_ok()
            }
            Some(host) => std::net::ToSocketAddrs::to_socket_addrs(&(host, 6000 + number))
                .ok()
                .and_then(|mut addresses| addresses.next())
                .is_some_and(|address| {
                    let timeout = Duration::from_millis(CONNECT_MS);
                    std::net::TcpStream::connect_timeout(&address, timeout).is_ok()
                }),
        };
        if reached {
            Ok(())
        } else {
            Err(format!(
                "--display: cannot reach the X display `{display}` (no graphical session?)"
            ))
        }
    }

    /// Without `DISPLAY`: the Wayland socket, if any.
    fn wayland() -> Result<(), String> {
        let missing = "--display needs a graphical session (neither DISPLAY nor \
                       WAYLAND_DISPLAY is set)";
        let name = std::env::var_os("WAYLAND_DISPLAY").ok_or(missing)?;
        let runtime = std::env::var_os("XDG_RUNTIME_DIR").unwrap_or_default();
        let socket = std::path::Path::new(&runtime).join(&name);
        if socket.exists() {
            Ok(())
        } else {
            Err(format!(
                "--display: no Wayland socket at {} (no graphical session?)",
                socket.display()
            ))
        }
    }

    /// `[host]:number[.screen]` → (host unless local, display number). `unix:0` is local.
    fn parse(display: &str) -> Option<(Option<&str>, u16)> {
        let (host, rest) = display.rsplit_once(':')?;
        let number = rest.split('.').next()?.parse::<u16>().ok()?;
        let host = Some(host).filter(|h| !h.is_empty() && *h != "unix");
        (number < 1000).then_some((host, number))
    }

    #[cfg(test)]
    mod tests {
        use super::parse;

        #[test]
        fn displays_parse() {
            assert_eq!(parse(":0"), Some((None, 0)));
            assert_eq!(parse(":1.0"), Some((None, 1)));
            assert_eq!(parse("unix:2"), Some((None, 2)));
            assert_eq!(parse("localhost:10.0"), Some((Some("localhost"), 10)));
            assert_eq!(parse("nonsense"), None);
            assert_eq!(parse(":x"), None);
        }
    }
}
