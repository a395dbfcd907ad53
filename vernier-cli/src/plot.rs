//! `vernier plot`: pose time series and Allan deviation of a pose table (the repeatability
//! view of metrologists), as a PNG, with a text summary on stdout.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use plotters::prelude::*;

use crate::pose_table::{read_table_file, PoseRow};

/// Arguments of `vernier plot`.
#[derive(Parser)]
pub struct PlotArgs {
    /// Pose table written by `vernier detect` or `vernier bag` (CSV or JSON Lines).
    input: PathBuf,
    /// Output PNG file.
    #[arg(long, short)]
    output: PathBuf,
    /// Image width, pixels.
    #[arg(long, default_value_t = 1600)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 1000)]
    height: u32,
}

/// Overlapping Allan deviation of the samples `y` (taken every `tau0`) at averaging times
/// `m·tau0`, `m = 1, 2, 4, …` while at least 2 non-overlapping pairs fit (`2m ≤ N − 1`):
/// `σ²(m) = mean_j (ȳ_{j+m} − ȳ_j)² / 2` with `ȳ_j` the mean of `y[j..j+m]`.
///
/// For white noise of standard deviation σ it falls as `σ/√m`; a floor or a rise reveals
/// drift. Returns `(tau, deviation)` pairs (deviation in the unit of `y`).
pub fn allan_deviation(y: &[f64], tau0: f64) -> Vec<(f64, f64)> {
    let n = y.len();
    let mut cumulative = Vec::with_capacity(n + 1);
    cumulative.push(0.0);
    for v in y {
        cumulative.push(cumulative.last().copied().unwrap_or(0.0) + v);
    }
    let mut out = Vec::new();
    let mut m = 1;
    while 2 * m < n {
        let mean = |j: usize| (cumulative[j + m] - cumulative[j]) / m as f64;
        let terms = n - 2 * m + 1;
        let sum: f64 = (0..terms).map(|j| (mean(j + m) - mean(j)).powi(2)).sum();
        out.push((m as f64 * tau0, (sum / (2.0 * terms as f64)).sqrt()));
        m *= 2;
    }
    out
}

/// Mean and (sample) standard deviation.
pub(crate) fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

/// One plotted quantity: name, unit, scale from the table's unit, and its column.
struct Quantity {
    name: &'static str,
    unit: &'static str,
    scale: f64,
    get: fn(&PoseRow) -> Option<f64>,
}

const QUANTITIES: [Quantity; 3] = [
    Quantity {
        name: "x",
        unit: "µm",
        scale: 1.0,
        get: |r| r.x,
    },
    Quantity {
        name: "y",
        unit: "µm",
        scale: 1.0,
        get: |r| r.y,
    },
    Quantity {
        name: "alpha",
        unit: "µrad",
        scale: 1e6,
        get: |r| r.alpha,
    },
];

/// The series of one marker: time (s, or frame index) and the rows.
pub(crate) struct Series<'a> {
    pub id: u64,
    pub time: Vec<f64>,
    pub rows: Vec<&'a PoseRow>,
}

/// Groups the rows with a pose by marker ID; time is the stamp relative to the first one
/// when every row has one, else the frame index.
pub(crate) fn series(rows: &[PoseRow]) -> (Vec<Series<'_>>, &'static str, f64) {
    let posed: Vec<&PoseRow> = rows
        .iter()
        .filter(|r| r.id.is_some() && r.x.is_some() && r.y.is_some())
        .collect();
    let use_stamp = !posed.is_empty() && posed.iter().all(|r| r.stamp.is_some());
    let t0 = posed
        .iter()
        .filter_map(|r| r.stamp)
        .fold(f64::INFINITY, f64::min);
    let mut by_id: BTreeMap<u64, Series> = BTreeMap::new();
    for r in posed {
        let id = r.id.unwrap_or(0);
        let s = by_id.entry(id).or_insert_with(|| Series {
            id,
            time: Vec::new(),
            rows: Vec::new(),
        });
        s.time.push(match (use_stamp, r.stamp) {
            (true, Some(t)) => t - t0,
            _ => r.frame as f64,
        });
        s.rows.push(r);
    }
    // Sampling interval: median step of the first series (1 frame without stamps).
    let mut steps: Vec<f64> = by_id
        .values()
        .next()
        .map(|s| {
            s.time
                .windows(2)
                .map(|w| w[1] - w[0])
                .filter(|d| *d > 0.0)
                .collect()
        })
        .unwrap_or_default();
    steps.sort_by(f64::total_cmp);
    let tau0 = steps.get(steps.len() / 2).copied().unwrap_or(1.0);
    let unit = if use_stamp { "s" } else { "frame" };
    (by_id.into_values().collect(), unit, tau0)
}

/// Runs `vernier plot`.
pub fn run(args: &PlotArgs) -> Result<ExitCode, String> {
    let rows = read_table_file(&args.input)?;
    let (all, time_unit, tau0) = series(&rows);
    if all.is_empty() {
        return Err(format!("{}: no pose to plot", args.input.display()));
    }
    if !(200..=10_000).contains(&args.width) || !(200..=10_000).contains(&args.height) {
        return Err("--width and --height must be within 200..=10000 pixels".into());
    }
    println!("id,quantity,unit,samples,mean,std,adev_tau0,tau0_{time_unit}");
    for s in &all {
        for q in &QUANTITIES {
            let v: Vec<f64> = s
                .rows
                .iter()
                .filter_map(|r| (q.get)(r))
                .map(|v| v * q.scale)
                .collect();
            if v.is_empty() {
                continue;
            }
            let (mean, std) = mean_std(&v);
            let adev = allan_deviation(&v, tau0).first().map_or(f64::NAN, |a| a.1);
            println!(
                "{},{},{},{},{mean},{std},{adev},{tau0}",
                s.id,
                q.name,
                q.unit,
                v.len()
            );
        }
    }
    let max = vernier::limits::MAX_RENDER_PIXELS;
    if args.width == 0 || args.height == 0 || u64::from(args.width) * u64::from(args.height) > max {
        return Err(format!(
            "--width {} --height {}: the plot must have 1 to {} pixels",
            args.width,
            args.height,
            vernier::limits::megapixels(max)
        ));
    }
    let mut pixels = vec![255u8; args.width as usize * args.height as usize * 3];
    draw(
        &all,
        time_unit,
        tau0,
        &mut pixels,
        (args.width, args.height),
    )
    .map_err(|e| format!("cannot draw the plot: {e}"))?;
    let image = image::RgbImage::from_raw(args.width, args.height, pixels)
        .ok_or("internal error: plot buffer size")?;
    // Encoded in memory, then written with every error checked (a full disk is an error).
    let mut png = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut png, image::ImageFormat::Png)
        .map_err(|e| format!("{}: {e}", args.output.display()))?;
    vernier::output::write_file(&args.output, png.get_ref())
        .map_err(|e| format!("{}: {e}", args.output.display()))?;
    Ok(ExitCode::SUCCESS)
}

/// Registers the embedded DejaVu Sans as the "sans-serif" family (once).
fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // An invalid font would only leave text out; DejaVu is known good.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

type DrawResult = Result<(), Box<dyn std::error::Error>>;

/// Left column: each quantity minus its mean against time; right column: Allan deviations.
fn draw(
    all: &[Series],
    time_unit: &str,
    tau0: f64,
    buffer: &mut [u8],
    size: (u32, u32),
) -> DrawResult {
    register_font();
    let root = BitMapBackend::with_buffer(buffer, size).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((QUANTITIES.len(), 2));
    for (qi, q) in QUANTITIES.iter().enumerate() {
        draw_time_series(&panels[2 * qi], all, q, time_unit)?;
        draw_allan_deviation(&panels[2 * qi + 1], all, q, tau0, time_unit)?;
    }
    root.present()?;
    Ok(())
}

/// A plot panel of the bitmap.
type Panel<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// A chart of `area` with `caption` above it and room for the axis labels: the frame both
/// columns of the plot share.
fn chart_builder<'a, 'b>(
    area: &'a Panel<'b>,
    caption: &str,
) -> ChartBuilder<'a, 'static, BitMapBackend<'b>> {
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(caption, ("sans-serif", 18))
        .margin(8)
        .x_label_area_size(30)
        .y_label_area_size(70);
    builder
}

/// Quantity `q` of each series minus its mean against time, in `area`.
fn draw_time_series(area: &Panel, all: &[Series], q: &Quantity, time_unit: &str) -> DrawResult {
    let mut lines = Vec::new();
    let (mut t_max, mut v_min, mut v_max) = (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for s in all {
        let v: Vec<(f64, f64)> = s
            .time
            .iter()
            .zip(&s.rows)
            .filter_map(|(t, r)| (q.get)(r).map(|v| (*t, v * q.scale)))
            .collect();
        if v.is_empty() {
            continue;
        }
        let mean = v.iter().map(|p| p.1).sum::<f64>() / v.len() as f64;
        let centred: Vec<(f64, f64)> = v.iter().map(|&(t, y)| (t, y - mean)).collect();
        for &(t, y) in &centred {
            t_max = t_max.max(t);
            v_min = v_min.min(y);
            v_max = v_max.max(y);
        }
        lines.push((s.id, centred));
    }
    let pad = ((v_max - v_min) * 0.05).max(1e-12);
    let mut chart = chart_builder(area, &format!("{} − mean ({})", q.name, q.unit))
        .build_cartesian_2d(0.0..t_max.max(1e-9), (v_min - pad)..(v_max + pad))?;
    chart
        .configure_mesh()
        .x_desc(format!("time ({time_unit})"))
        .label_style(("sans-serif", 13))
        .draw()?;
    for (k, (id, points)) in lines.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(
                points.iter().copied(),
                color.stroke_width(1),
            ))?
            .label(format!("id {id}"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], color));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()?;
    Ok(())
}

/// The Allan deviation of quantity `q` of each series against averaging time, log-log, in
/// `area` (or a title saying there are too few samples).
fn draw_allan_deviation(
    area: &Panel,
    all: &[Series],
    q: &Quantity,
    tau0: f64,
    time_unit: &str,
) -> DrawResult {
    let curves: Vec<(u64, Vec<(f64, f64)>)> = all
        .iter()
        .map(|s| {
            let v: Vec<f64> = s
                .rows
                .iter()
                .filter_map(|r| (q.get)(r))
                .map(|v| v * q.scale)
                .collect();
            (
                s.id,
                allan_deviation(&v, tau0)
                    .into_iter()
                    .filter(|p| p.1 > 0.0)
                    .collect::<Vec<_>>(),
            )
        })
        .filter(|(_, c)| !c.is_empty())
        .collect();
    if curves.is_empty() {
        area.titled("Allan deviation: too few samples", ("sans-serif", 18))?;
        return Ok(());
    }
    let (mut t_lo, mut t_hi, mut d_lo, mut d_hi) = (f64::INFINITY, 0.0f64, f64::INFINITY, 0.0f64);
    for (_, c) in &curves {
        for &(t, d) in c {
            t_lo = t_lo.min(t);
            t_hi = t_hi.max(t);
            d_lo = d_lo.min(d);
            d_hi = d_hi.max(d);
        }
    }
    // At least a decade per axis, so that the log axes get labelled ticks.
    let widen = |lo: f64, hi: f64| {
        let centre = (lo * hi).sqrt();
        let half = (hi / lo).sqrt().max(10f64.sqrt()) * 1.5;
        (centre / half, centre * half)
    };
    let ((t_lo, t_hi), (d_lo, d_hi)) = (widen(t_lo, t_hi), widen(d_lo, d_hi));
    let mut chart = chart_builder(area, &format!("Allan deviation of {} ({})", q.name, q.unit))
        .build_cartesian_2d((t_lo..t_hi).log_scale(), (d_lo..d_hi).log_scale())?;
    chart
        .configure_mesh()
        .x_desc(format!("averaging time τ ({time_unit})"))
        .y_label_formatter(&|v| format!("{v:.1e}"))
        .label_style(("sans-serif", 13))
        .draw()?;
    for (k, (_, c)) in curves.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        chart.draw_series(LineSeries::new(c.iter().copied(), color.stroke_width(2)))?;
        chart.draw_series(c.iter().map(|&p| Circle::new(p, 3, color.filled())))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allan_deviation_of_white_noise_falls_as_one_over_sqrt_tau() {
        // Deterministic pseudo-random white noise, σ ≈ 1 (sum of 12 uniforms − 6).
        let mut state = 12345u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let y: Vec<f64> = (0..4096)
            .map(|_| (0..12).map(|_| uniform()).sum::<f64>() - 6.0)
            .collect();
        let adev = allan_deviation(&y, 0.5);
        assert_eq!(adev[0].0, 0.5);
        assert!((adev[0].1 - 1.0).abs() < 0.05, "{:?}", adev[0]);
        let m16 = adev.iter().find(|p| p.0 == 8.0).unwrap();
        assert!((m16.1 - 0.25).abs() < 0.04, "{m16:?}");
        // A linear drift makes the deviation grow with τ.
        let drift: Vec<f64> = (0..256).map(|i| i as f64).collect();
        let d = allan_deviation(&drift, 1.0);
        assert!(d.windows(2).all(|w| w[1].1 > w[0].1));
        assert!((d[0].1 - 1.0 / 2f64.sqrt()).abs() < 1e-12);
        assert!(allan_deviation(&[1.0, 2.0], 1.0).is_empty());
    }
}
