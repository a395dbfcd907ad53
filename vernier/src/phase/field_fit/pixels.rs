//! The field's pixel box ([`FieldBox`]), its tilt warp ([`Warp`]) and the iterator of the
//! pixels that a sweep visits ([`FieldPixels`]).

use super::*;

/// One pixel of the field as the sweeps see it.
pub(super) struct Pixel {
    /// Normalised coordinates.
    pub(super) xn: f64,
    pub(super) yn: f64,
    pub(super) g: f64,
    /// Layout weight `w_L`.
    pub(super) layout: f64,
    /// Layout weight with the nodes' robust weights.
    pub(super) w: f64,
    /// `e^{iφ_l}`.
    pub(super) z: [Complex64; 2],
    /// The planes' linear lattice coordinates `φ_lin,l/2π`, periods (their node numbering):
    /// the lattice coordinates themselves unless the field has a [`Warp`].
    pub(super) linear: [f64; 2],
    /// `∂u_l/∂v_m`, the lattice coordinates' derivatives along the linear ones (identity
    /// without a [`Warp`]) …
    pub(super) jacobian: [[f64; 2]; 2],
    /// … and `1/D²`, `D = 1 − p·v` (1 without one).
    pub(super) inverse_square: f64,
    /// Index of the nearest node (the pixel's cell) in per-node arrays, if inside the mask.
    pub(super) cell: Option<usize>,
    /// Columns since the previous pixel visited in this row; 0 for the first of the row,
    /// [`RESEED`] where the bank is to be seeded afresh within the row (a warped field).
    pub(super) advance: usize,
    /// `e^{i(φ_l(x + 1) − φ_l(x))}`, the phase step to the next column …
    pub(super) step: [Complex64; 2],
    /// … and how it turns per column, `e^{iΔ²φ_l}` (1 on a field without a [`Warp`]).
    pub(super) chirp: [Complex64; 2],
    /// The field has a [`Warp`].
    pub(super) warped: bool,
    /// Row-major index of the pixel in the field's box.
    pub(super) index: usize,
}

/// The field's pixel box: pixels within one period of the regular nodes, clipped to the image
/// ([`FieldBox::new`]: its bounds, coordinates normalised by its half-size; [`first_model`]
/// centres them on the field's layout weight).
pub(super) struct FieldBox {
    pub(super) cols: std::ops::Range<usize>,
    pub(super) rows: std::ops::Range<usize>,
    /// Image-frame origin `(C div 2, R div 2)`.
    pub(super) center: (f64, f64),
    /// Normalisation `(x₀, y₀, s)`.
    pub(super) frame: (f64, f64, f64),
    /// Clearance factor of each pixel of the box (row-major; [`NodeMask::clearance`]), set
    /// once per fit on the start planes by [`FieldBox::set_clearance`]: the fit moves the
    /// planes by a small fraction of a cell, and the distance search is the costliest part of
    /// a pixel's weight.
    pub(super) clearance: Vec<f32>,
    /// Per row of the box, the columns from the first to the last pixel of non-zero clearance
    /// (the sweeps skip the rest: the corners of a turned marker's box, the image beyond it).
    pub(super) spans: Vec<std::ops::Range<usize>>,
    /// The perspective in the phase model, if any.
    pub(super) warp: Option<Warp>,
}

/// A perspective built into the phase model: the second pass of a tilted field's fit
/// (docs/design.md#tilt-centre). Lattice coordinates `u = c + v/(1 − p·v)`, `v = u_lin − c`
/// the planes' linear coordinates about the tilt centre `c`: the planes are the tangent planes
/// of the lattice at `c`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Warp {
    /// `p`, per period.
    pub(super) perspective: Vector2<f64>,
    /// `c`, periods, in the planes' numbering.
    pub(super) centre: [f64; 2],
}

impl Warp {
    /// Lattice coordinates of the linear ones `lin`, with `∂u_l/∂v_m = δ_lm/D + v_l·p_m/D²`
    /// and `1/D²`; `None` beyond the horizon's neighbourhood (`D ≤ 1/2`, a perspective no
    /// microscope gives over a marker: `p·v` is a few 10⁻² at 25° before a short lens).
    #[inline(always)]
    pub(super) fn apply(&self, lin: [f64; 2]) -> Option<([f64; 2], [[f64; 2]; 2], f64)> {
        let (p, c) = (self.perspective, self.centre);
        let v = [lin[0] - c[0], lin[1] - c[1]];
        let d = 1.0 - (p.x * v[0] + p.y * v[1]);
        // NaN fails too.
        if d.is_nan() || d <= 0.5 {
            return None;
        }
        let inverse = 1.0 / d;
        let square = inverse * inverse;
        let u = [c[0] + v[0] * inverse, c[1] + v[1] * inverse];
        let jacobian = [
            [inverse + v[0] * p.x * square, v[0] * p.y * square],
            [v[1] * p.x * square, inverse + v[1] * p.y * square],
        ];
        Some((u, jacobian, square))
    }
}

impl FieldBox {
    pub(super) fn new(
        image: &GreyImage,
        planes: &[PhasePlane; 2],
        mask: &NodeMask,
    ) -> Option<Self> {
        let m = nalgebra::Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
        let inverse = m.try_inverse()?;
        let (mut lo, mut hi) = (
            Vector2::repeat(f64::INFINITY),
            Vector2::repeat(f64::NEG_INFINITY),
        );
        let (a0, b0) = mask.first;
        let (a1, b1) = (a0 + mask.dims.0 as i64, b0 + mask.dims.1 as i64);
        for (k1, k2) in [(a0 - 1, b0 - 1), (a0 - 1, b1), (a1, b0 - 1), (a1, b1)] {
            let phase = Vector2::new(TAU * k1 as f64 - planes[0].c, TAU * k2 as f64 - planes[1].c);
            let p = inverse * phase;
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let (cx, cy) = image.center();
        let (cx, cy) = (cx as f64, cy as f64);
        let clip = |v: f64, n: usize| (v.max(0.0).min(n as f64)) as usize;
        if !(lo.iter().chain(hi.iter()).all(|v| v.is_finite())) {
            return None;
        }
        let cols =
            clip((lo.x + cx).floor(), image.width())..clip((hi.x + cx).ceil() + 1.0, image.width());
        let rows = clip((lo.y + cy).floor(), image.height())
            ..clip((hi.y + cy).ceil() + 1.0, image.height());
        if cols.is_empty() || rows.is_empty() {
            return None;
        }
        let s = (cols.len().max(rows.len()) as f64 / 2.0).max(1.0);
        Some(FieldBox {
            cols,
            rows,
            center: (cx, cy),
            frame: (0.0, 0.0, s),
            clearance: Vec::new(),
            spans: Vec::new(),
            warp: None,
        })
    }

    /// The frame position of the box's pixel `(0, 0)`, pixels.
    pub(super) fn origin(&self) -> Vector2<f64> {
        Vector2::new(
            self.cols.start as f64 - self.center.0,
            self.rows.start as f64 - self.center.1,
        )
    }

    /// Fills [`FieldBox::clearance`] for `mask` at the lattice coordinates of `planes`.
    pub(super) fn set_clearance(&mut self, planes: &[PhasePlane; 2], mask: &NodeMask) {
        let mut clearance = Vec::with_capacity(self.rows.len() * self.cols.len());
        let mut spans = Vec::with_capacity(self.rows.len());
        for row in self.rows.clone() {
            let y = row as f64 - self.center.1;
            let start = clearance.len();
            for col in self.cols.clone() {
                let x = col as f64 - self.center.0;
                let lin = planes.map(|p| p.at(x, y) / TAU);
                let clear = match &self.warp {
                    None => mask.clearance(lin.map(|u| 2.0 * u)),
                    Some(warp) => warp
                        .apply(lin)
                        .map_or(0.0, |(u, _, _)| mask.clearance(u.map(|u| 2.0 * u))),
                };
                clearance.push(clear as f32);
            }
            let row_values = &clearance[start..];
            let first = row_values.iter().position(|&c| c > 0.0);
            let last = row_values.iter().rposition(|&c| c > 0.0);
            spans.push(match (first, last) {
                (Some(a), Some(b)) => self.cols.start + a..self.cols.start + b + 1,
                _ => self.cols.start..self.cols.start,
            });
        }
        self.clearance = clearance;
        self.spans = spans;
    }

    /// The columns of `row` that the sweeps visit (all before [`FieldBox::set_clearance`]).
    pub(super) fn span(&self, row: usize) -> std::ops::Range<usize> {
        self.spans
            .get(row - self.rows.start)
            .cloned()
            .unwrap_or(self.cols.clone())
    }

    /// The pixels of the field with a non-zero layout weight, row by row; `nodes` holds the
    /// nodes' robust weights (empty: all 1).
    pub(super) fn pixels<'a>(
        &'a self,
        image: &'a GreyImage,
        planes: &[PhasePlane; 2],
        mask: &'a NodeMask,
        nodes: &'a [f64],
    ) -> FieldPixels<'a> {
        FieldPixels {
            field: self,
            pixels: image.pixels(),
            width: image.width(),
            planes: *planes,
            mask,
            weights: NodeWeights::new(mask, nodes),
            step: planes.map(|p| Complex64::from_polar(1.0, p.a)),
            half_step: planes.map(|p| Complex64::from_polar(1.0, 0.5 * p.a)),
            chirp: [Complex64::new(1.0, 0.0); 2],
            half_chirp: [Complex64::new(1.0, 0.0); 2],
            exact_at: 0,
            reseeded: false,
            half: [Complex64::default(); 2],
            row: self.rows.start,
            col: self.cols.start,
            fresh_row: true,
            z: [Complex64::default(); 2],
            last: None,
            row_end: self.cols.start,
            flat: FlatRow::new(planes, self.cols.len()),
        }
    }
}

/// Columns per block of a flat row's phase rotors ([`FlatRow`]).
const ROTOR_BLOCK: usize = 8;

/// A flat field's (no [`Warp`]) visited pixels of one row, computed in one pass over the
/// row's span before the sweep takes them: each pixel's phases from its block's rotor and a
/// table of powers of the column step (no chain of products along the row), its lattice
/// coordinates, layout weight and intensity, with no sweep state in between.
pub(super) struct FlatRow {
    /// The planes over `2π`: lattice coordinates per pixel.
    cycles: [PhasePlane; 2],
    /// `e^{ija_l/2}` for `j < ROTOR_BLOCK`, and `e^{ia_l/2·ROTOR_BLOCK}`.
    powers: [[Complex64; ROTOR_BLOCK]; 2],
    block_step: [Complex64; 2],
    /// The row's visited pixels, in column order, and the next one to hand out.
    pixels: Vec<FlatPixel>,
    next: usize,
    /// The row they are on.
    row: usize,
}

/// One pixel of a [`FlatRow`].
#[derive(Clone, Copy)]
struct FlatPixel {
    col: usize,
    xn: f64,
    g: f64,
    layout: f64,
    w: f64,
    z: [Complex64; 2],
    linear: [f64; 2],
    cell: Option<usize>,
}

impl FlatRow {
    fn new(planes: &[PhasePlane; 2], capacity: usize) -> Self {
        let half_turn = |p: &PhasePlane, j: usize| Complex64::from_polar(1.0, 0.5 * p.a * j as f64);
        FlatRow {
            cycles: planes.map(|p| PhasePlane {
                a: p.a / TAU,
                b: p.b / TAU,
                c: p.c / TAU,
            }),
            powers: planes.map(|p| std::array::from_fn(|j| half_turn(&p, j))),
            block_step: planes.map(|p| half_turn(&p, ROTOR_BLOCK)),
            pixels: Vec::with_capacity(capacity),
            next: 0,
            row: 0,
        }
    }
}

/// Iterator over the pixels of a [`FieldBox`] (a plain loop, so that it inlines into the
/// vectorised fit; closures would not inherit its target features).
pub(super) struct FieldPixels<'a> {
    pub(super) field: &'a FieldBox,
    pub(super) pixels: &'a [f32],
    pub(super) width: usize,
    pub(super) planes: [PhasePlane; 2],
    pub(super) mask: &'a NodeMask,
    pub(super) weights: NodeWeights,
    /// `e^{ia_l}`: one column's phase step.
    pub(super) step: [Complex64; 2],
    /// `e^{ia_l/2}`.
    pub(super) half_step: [Complex64; 2],
    /// A warped field's phases advance by a step that changes along the row: `step` is the
    /// one from the current column to the next, and it turns by `chirp`, `e^{iΔ²φ_l}`, per
    /// column (the second difference of the phase; `half_chirp` for the half phases). Exact
    /// values are computed every [`WARP_EXACT_COLUMNS`] columns, at `exact_at`, …
    pub(super) chirp: [Complex64; 2],
    pub(super) half_chirp: [Complex64; 2],
    pub(super) exact_at: usize,
    /// … and the bank is seeded afresh at the next pixel visited after that.
    pub(super) reseeded: bool,
    /// `e^{iφ_l/2}` at `(col, row)`: `cos πu_l` for the layout weight.
    pub(super) half: [Complex64; 2],
    pub(super) row: usize,
    /// Next column.
    pub(super) col: usize,
    /// `z` must be computed afresh (start of a row).
    pub(super) fresh_row: bool,
    /// `e^{iφ_l}` at `(col, row)`.
    pub(super) z: [Complex64; 2],
    /// Last column visited in this row.
    pub(super) last: Option<usize>,
    /// End of this row's span ([`FieldBox::span`]).
    pub(super) row_end: usize,
    /// A flat field's current row.
    pub(super) flat: FlatRow,
}

impl FieldPixels<'_> {
    /// Starts the current row at its span's first column (phases computed afresh); `false`
    /// when the row has no span.
    #[inline(always)]
    fn start_row(&mut self) -> bool {
        let f = self.field;
        let span = f.span(self.row);
        if span.is_empty() {
            return false;
        }
        self.fresh_row = false;
        self.last = None;
        self.col = span.start;
        self.row_end = span.end;
        let y = self.row as f64 - f.center.1;
        let x = self.col as f64 - f.center.0;
        match &f.warp {
            None => {
                self.z = self.planes.map(|p| Complex64::from_polar(1.0, p.at(x, y)));
                self.half = self
                    .planes
                    .map(|p| Complex64::from_polar(1.0, 0.5 * p.at(x, y)));
            }
            Some(warp) => self.set_exact(warp, x, y),
        }
        true
    }

    /// Moves one column along the row: the phases by their steps, and a warped field's steps
    /// by their chirps.
    #[inline(always)]
    fn next_column(&mut self) {
        let (z, half) = (self.z, self.half);
        self.col += 1;
        self.z = [z[0] * self.step[0], z[1] * self.step[1]];
        self.half = [half[0] * self.half_step[0], half[1] * self.half_step[1]];
        if self.field.warp.is_some() {
            self.step = [self.step[0] * self.chirp[0], self.step[1] * self.chirp[1]];
            self.half_step = [
                self.half_step[0] * self.half_chirp[0],
                self.half_step[1] * self.half_chirp[1],
            ];
        }
    }

    /// Sets the phases of a warped field exactly at image-frame `(x, y)` (the current column),
    /// with their step to the next column and its turn per column, from the phases at the next
    /// two columns; leaves them as they are where the warp does not reach those columns.
    #[inline(always)]
    pub(super) fn set_exact(&mut self, warp: &Warp, x: f64, y: f64) {
        let phase = |dx: f64| {
            let linear = self.planes.map(|p| p.at(x + dx, y) / TAU);
            warp.apply(linear)
                .map_or([f64::NAN; 2], |(u, _, _)| u.map(|u| TAU * u))
        };
        let (p0, p1, p2) = (phase(0.0), phase(1.0), phase(2.0));
        if [p0, p1, p2].iter().flatten().any(|v| !v.is_finite()) {
            // Beyond the warp's reach ([`Warp::apply`]): tried again at the next column.
            return;
        }
        let polar = |v: [f64; 2], k: f64| v.map(|v| Complex64::from_polar(1.0, k * v));
        let step = [p1[0] - p0[0], p1[1] - p0[1]];
        let chirp = [p2[0] - 2.0 * p1[0] + p0[0], p2[1] - 2.0 * p1[1] + p0[1]];
        self.z = polar(p0, 1.0);
        self.half = polar(p0, 0.5);
        self.step = polar(step, 1.0);
        self.half_step = polar(step, 0.5);
        self.chirp = polar(chirp, 1.0);
        self.half_chirp = polar(chirp, 0.5);
        self.exact_at = self.col;
    }
}

impl FieldPixels<'_> {
    /// Fills [`FieldPixels::flat`] with the visited pixels of row `row` of a flat field.
    #[inline(always)]
    fn fill_flat_row(&mut self, row: usize) {
        let f = self.field;
        let flat = &mut self.flat;
        flat.pixels.clear();
        flat.next = 0;
        flat.row = row;
        let span = f.span(row);
        if span.is_empty() {
            return;
        }
        let (x0, _, s) = f.frame;
        let inverse_scale = 1.0 / s;
        let y = row as f64 - f.center.1;
        let x_start = span.start as f64 - f.center.0;
        let mut seed = self
            .planes
            .map(|p| Complex64::from_polar(1.0, 0.5 * p.at(x_start, y)));
        let base = (row - f.rows.start) * f.cols.len();
        let clearance = f
            .clearance
            .get(base + (span.start - f.cols.start)..base + (span.end - f.cols.start))
            .unwrap_or(&[]);
        let pixels = self.pixels.get(row * self.width..).unwrap_or(&[]);
        for (block, clear) in clearance.chunks(ROTOR_BLOCK).enumerate() {
            for (j, &clear) in clear.iter().enumerate() {
                if clear <= 0.0 {
                    continue;
                }
                let col = span.start + block * ROTOR_BLOCK + j;
                let x = col as f64 - f.center.0;
                let half = [seed[0] * flat.powers[0][j], seed[1] * flat.powers[1][j]];
                let linear = flat.cycles.map(|p| p.at(x, y));
                let (layout, w) = self.weights.weight(linear, [half[0].re, half[1].re]);
                let (layout, w) = (layout * clear as f64, w * clear as f64);
                let g = pixels.get(col).copied().unwrap_or(f32::NAN) as f64;
                if layout > 0.0 && g.is_finite() {
                    flat.pixels.push(FlatPixel {
                        col,
                        xn: (x - x0) * inverse_scale,
                        g,
                        layout,
                        w,
                        z: [half[0] * half[0], half[1] * half[1]],
                        linear,
                        cell: self
                            .mask
                            .index(linear[0].round() as i64, linear[1].round() as i64),
                    });
                }
            }
            seed = [seed[0] * flat.block_step[0], seed[1] * flat.block_step[1]];
        }
    }

    /// The next pixel of a flat field.
    #[inline(always)]
    fn next_flat(&mut self) -> Option<Pixel> {
        let f = self.field;
        while self.flat.next >= self.flat.pixels.len() {
            if self.row >= f.rows.end {
                return None;
            }
            self.fill_flat_row(self.row);
            self.row += 1;
            self.last = None;
        }
        let q = *self.flat.pixels.get(self.flat.next)?;
        self.flat.next += 1;
        let row = self.flat.row;
        let advance = self.last.map_or(0, |l| q.col - l);
        self.last = Some(q.col);
        let (_, y0, s) = f.frame;
        Some(Pixel {
            xn: q.xn,
            yn: (row as f64 - f.center.1 - y0) / s,
            g: q.g,
            layout: q.layout,
            w: q.w,
            z: q.z,
            step: self.step,
            chirp: [Complex64::new(1.0, 0.0); 2],
            warped: false,
            linear: q.linear,
            jacobian: [[1.0, 0.0], [0.0, 1.0]],
            inverse_square: 1.0,
            cell: q.cell,
            advance,
            index: (row - f.rows.start) * f.cols.len() + (q.col - f.cols.start),
        })
    }
}

impl Iterator for FieldPixels<'_> {
    type Item = Pixel;

    #[inline(always)]
    fn next(&mut self) -> Option<Pixel> {
        if self.field.warp.is_none() {
            self.next_flat()
        } else {
            self.next_warped()
        }
    }
}

impl FieldPixels<'_> {
    /// The next pixel of a field with the tilt in its phase model ([`Warp`]).
    #[inline(always)]
    fn next_warped(&mut self) -> Option<Pixel> {
        let f = self.field;
        let (x0, y0, s) = f.frame;
        loop {
            if self.row >= f.rows.end {
                return None;
            }
            if self.fresh_row && !self.start_row() {
                self.row += 1;
                continue;
            }
            if let Some(warp) = &f.warp {
                if self.col >= self.exact_at + WARP_EXACT_COLUMNS {
                    let y = self.row as f64 - f.center.1;
                    self.set_exact(warp, self.col as f64 - f.center.0, y);
                    self.reseeded = true;
                }
            }
            if self.col >= self.row_end {
                self.row += 1;
                self.fresh_row = true;
                continue;
            }
            let (row, col) = (self.row, self.col);
            let x = col as f64 - f.center.0;
            let y = row as f64 - f.center.1;
            let (z, half, step) = (self.z, self.half, self.step);
            self.next_column();
            let index = (row - f.rows.start) * f.cols.len() + (col - f.cols.start);
            let clear = f.clearance.get(index).copied().unwrap_or(0.0) as f64;
            if clear <= 0.0 {
                // On a discrepant cell (a finder, a missing dot) or outside the field: no
                // weight, whatever the nodes', so theirs are not computed.
                continue;
            }
            let linear = [self.planes[0].at(x, y) / TAU, self.planes[1].at(x, y) / TAU];
            let (u, jacobian, inverse_square) = match &f.warp {
                None => (linear, [[1.0, 0.0], [0.0, 1.0]], 1.0),
                Some(warp) => match warp.apply(linear) {
                    Some(applied) => applied,
                    None => continue,
                },
            };
            let (layout, w) = self.weights.weight(u, [half[0].re, half[1].re]);
            let (layout, w) = (layout * clear, w * clear);
            let g = self
                .pixels
                .get(row * self.width + col)
                .copied()
                .unwrap_or(f32::NAN) as f64;
            if layout > 0.0 && g.is_finite() {
                let advance = match self.last {
                    None => 0,
                    Some(_) if self.reseeded => RESEED,
                    Some(l) => col - l,
                };
                self.reseeded = false;
                self.last = Some(col);
                return Some(Pixel {
                    xn: (x - x0) / s,
                    yn: (y - y0) / s,
                    g,
                    layout,
                    w,
                    z,
                    step,
                    chirp: self.chirp,
                    warped: f.warp.is_some(),
                    linear,
                    jacobian,
                    inverse_square,
                    cell: self.mask.index(u[0].round() as i64, u[1].round() as i64),
                    advance,
                    index,
                });
            }
        }
    }
}
