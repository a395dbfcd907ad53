//! The layout of a marker's dot field on the half-period cell grid ([`NodeMask`]), its
//! clearance around discrepant cells and the nodes' weights of one sweep.

use super::*;

/// The layout of a marker's dot field, on the half-period cell grid of the planes given to
/// [`fit_dot_field`]: cell `(v₁, v₂)` is centred where `φ_l = π·v_l`, so the lattice nodes
/// (dot centres, `φ_l = 2πk_l`) are the cells `(2k₁, 2k₂)`. A cell is *discrepant* where the
/// layout differs from the periodic dot grid: a missing dot, ink on an odd cell (finder, frame,
/// glyph) or the marker's edge. The fit weighs the pixels around every drawn dot, less within
/// one period (more on blurred images) of a discrepant cell and not at all on one.
#[derive(Clone, Debug)]
pub struct NodeMask {
    pub(super) first: (i64, i64),
    pub(super) dims: (usize, usize),
    /// Per node: its dot is drawn.
    pub(super) present: Vec<bool>,
    /// Cell `(v₁, v₂)` of entry `(0, 0)` of the cell maps.
    pub(super) first_cell: (i64, i64),
    /// Extent of the cell maps.
    pub(super) cell_dims: (usize, usize),
    /// Per cell: the layout differs from the periodic grid there.
    pub(super) discrepant: Vec<bool>,
    /// Taper length from discrepant cells, cells.
    pub(super) clearance: f64,
    /// The discrepant cells within `ceil(clearance)` cells of each cell (pixels of a cell with
    /// none are at least `clearance` away from every discrepant one), as offsets from it,
    /// nearest first: cell `i`'s are `nearby[nearby_start[i]..nearby_start[i + 1]]`. Most
    /// cells have none or a few of the `(2·ceil(c) + 1)²` around them, so a pixel's distance
    /// search looks at those only.
    pub(super) nearby: Vec<(i8, i8)>,
    pub(super) nearby_start: Vec<usize>,
}

/// Shortest distance from a discrepant cell's square, in half-period cells, over which a
/// pixel's weight rises from 0 to 1 (`sin²`): one period. A blurred image gets
/// [`CLEARANCE_PER_BLUR`] cells per period of blur σ when that is longer
/// ([`NodeMask::with_clearance_for_blur`]).
pub(super) const MIN_CLEARANCE: f64 = 2.0;

/// Clearance per unit of blur σ (both in cells): the edge of a finder, a frame or a missing
/// dot departs from the periodic model by ~`Φ(−d/σ)` of its contrast at distance `d`, so six
/// σ of taper keep that departure, weighted, below 1e-4 (a stress scene at σ = P/4: 4e-4 px
/// of bias with a one-period taper, 1e-5–2.4e-4 px with six σ).
pub(super) const CLEARANCE_PER_BLUR: f64 = 6.0;

/// Longest clearance, cells (blur beyond σ = P/3 leaves the dots too faint to measure).
pub(super) const MAX_CLEARANCE: f64 = 4.0;

/// Cells beyond the nodes that the cell maps cover: a weighted pixel is within one period (2
/// cells) of a drawn dot and looks at cells up to [`MAX_CLEARANCE`] from its own.
pub(super) const CELL_MARGIN: i64 = 3 + MAX_CLEARANCE as i64;

/// `|A₁₁|/|B|`, the (1, ±1) harmonics' amplitude over the fundamental's, of sharp round dots
/// half a period wide (square ones: 0.64); blur σ (periods) lowers it by `e^{−2π²σ²}`.
pub(super) const SHARP_DIAGONAL_RATIO: f64 = 0.70;

impl NodeMask {
    /// The nodes `k₁ ∈ k1`, `k₂ ∈ k2` of a layout whose half-period cell `(v₁, v₂)` holds ink
    /// where `ink(v₁, v₂)` (also asked for cells up to a few beyond the nodes; `false` outside
    /// the marker).
    pub fn from_cells(
        k1: std::ops::RangeInclusive<i64>,
        k2: std::ops::RangeInclusive<i64>,
        ink: impl Fn(i64, i64) -> bool,
    ) -> Self {
        let count = |r: &std::ops::RangeInclusive<i64>| (r.end() - r.start() + 1).max(0) as usize;
        let dims = (count(&k1), count(&k2));
        let mut present = Vec::with_capacity(dims.0 * dims.1);
        for a in k1.clone() {
            for b in k2.clone() {
                present.push(ink(2 * a, 2 * b));
            }
        }
        let first_cell = (2 * k1.start() - CELL_MARGIN, 2 * k2.start() - CELL_MARGIN);
        let cell_dims = (
            (2 * dims.0 as i64 - 1 + 2 * CELL_MARGIN).max(0) as usize,
            (2 * dims.1 as i64 - 1 + 2 * CELL_MARGIN).max(0) as usize,
        );
        let cell = |i: usize, j: usize| (first_cell.0 + i as i64, first_cell.1 + j as i64);
        let mut discrepant = Vec::with_capacity(cell_dims.0 * cell_dims.1);
        for i in 0..cell_dims.0 {
            for j in 0..cell_dims.1 {
                let (v1, v2) = cell(i, j);
                let periodic = v1.rem_euclid(2) == 0 && v2.rem_euclid(2) == 0;
                discrepant.push(ink(v1, v2) != periodic);
            }
        }
        let mut mask = NodeMask {
            first: (*k1.start(), *k2.start()),
            dims,
            present,
            first_cell,
            cell_dims,
            discrepant,
            clearance: MIN_CLEARANCE,
            nearby: Vec::new(),
            nearby_start: Vec::new(),
        };
        mask.list_nearby_discrepant();
        mask
    }

    /// The same mask with the taper lengthened for the blur measured on `model` (σ in
    /// periods from the (1, ±1) harmonics, [`SHARP_DIAGONAL_RATIO`]); `None` when the
    /// shortest one fits.
    pub(super) fn with_clearance_for_blur(&self, model: &Model) -> Option<NodeMask> {
        let diagonal: Vec<f64> = model
            .harmonics
            .iter()
            .filter(|((h1, h2), _)| *h1 == 1 && h2.abs() == 1)
            .map(|(_, a)| a.norm())
            .collect();
        let contrast = model.contrast();
        if contrast <= 0.0 {
            return None;
        }
        // Harmonics too faint to be modelled: blur well beyond a quarter period.
        let ratio = (diagonal.iter().sum::<f64>() / diagonal.len().max(1) as f64 / contrast)
            .max(MIN_HARMONIC);
        let sigma = ((SHARP_DIAGONAL_RATIO / ratio).ln().max(0.0) / (2.0 * PI * PI)).sqrt();
        let clearance = (CLEARANCE_PER_BLUR * 2.0 * sigma).clamp(MIN_CLEARANCE, MAX_CLEARANCE);
        (clearance > MIN_CLEARANCE).then(|| {
            let mut wider = self.clone();
            wider.clearance = clearance;
            wider.list_nearby_discrepant();
            wider
        })
    }

    /// Fills `nearby` and `nearby_start` for the current clearance.
    pub(super) fn list_nearby_discrepant(&mut self) {
        // At most MAX_CLEARANCE cells: offsets fit in a byte.
        let reach = self.clearance.ceil().min(MAX_CLEARANCE) as i8;
        let mut offsets: Vec<(i8, i8)> = (-reach..=reach)
            .flat_map(|da| (-reach..=reach).map(move |db| (da, db)))
            .collect();
        offsets.sort_by_key(|&(da, db)| i32::from(da).pow(2) + i32::from(db).pow(2));
        let ((v1, v2), (n1, n2)) = (self.first_cell, self.cell_dims);
        let (mut nearby, mut starts) = (Vec::new(), Vec::with_capacity(n1 * n2 + 1));
        for a in v1..v1 + n1 as i64 {
            for b in v2..v2 + n2 as i64 {
                starts.push(nearby.len());
                let discrepant = offsets
                    .iter()
                    .filter(|&&(da, db)| self.is_discrepant(a + i64::from(da), b + i64::from(db)));
                nearby.extend(discrepant);
            }
        }
        starts.push(nearby.len());
        self.nearby = nearby;
        self.nearby_start = starts;
    }

    /// The discrepant cells near cell index `i`, as offsets from it, nearest first.
    pub(super) fn nearby_discrepant(&self, i: usize) -> &[(i8, i8)] {
        match (self.nearby_start.get(i), self.nearby_start.get(i + 1)) {
            (Some(&start), Some(&end)) => self.nearby.get(start..end).unwrap_or(&[]),
            _ => &[],
        }
    }

    /// Whether the dot of node `(k1, k2)` is drawn.
    pub fn get(&self, k1: i64, k2: i64) -> bool {
        self.index(k1, k2).is_some_and(|i| self.present[i])
    }

    /// Index of node `(k1, k2)` in per-node arrays of [`NodeMask::len`] entries.
    pub(super) fn index(&self, k1: i64, k2: i64) -> Option<usize> {
        grid_index(self.first, self.dims, k1, k2)
    }

    /// Index of cell `(v1, v2)` in the cell maps.
    pub(super) fn cell_index(&self, v1: i64, v2: i64) -> Option<usize> {
        grid_index(self.first_cell, self.cell_dims, v1, v2)
    }

    /// Whether cell `(v1, v2)` is discrepant (false outside the cell maps).
    pub(super) fn is_discrepant(&self, v1: i64, v2: i64) -> bool {
        self.cell_index(v1, v2).is_some_and(|i| self.discrepant[i])
    }

    /// Weight factor in `[0, 1]` of a pixel at cell coordinates `v = 2u`: `sin²(π·d/2c)` of its
    /// distance `d` from the nearest discrepant cell's square, in cells, 1 from the clearance
    /// `c` on (the Euclidean distance: the blur is isotropic).
    #[inline(always)]
    pub(super) fn clearance(&self, v: [f64; 2]) -> f64 {
        let (c1, c2) = (v[0].round() as i64, v[1].round() as i64);
        let Some(i) = self.cell_index(c1, c2) else {
            return 0.0;
        };
        let nearby = self.nearby_discrepant(i);
        if nearby.is_empty() {
            return 1.0;
        }
        // Squared distances in the search, one root at the end; a pixel on a discrepant cell
        // (offset (0, 0), listed first) is at distance 0, the least there is. Only distances
        // under the clearance matter (1 beyond), and the cells come nearest first: a cell at
        // offset d is at least |d| − √2 from any pixel of this one, so the search stops at the
        // first offset with |d|² ≥ (√2 + nearest)², past which none can come nearer.
        let limit = self.clearance * self.clearance;
        let stop_at = |nearest2: f64| (std::f64::consts::SQRT_2 + nearest2.sqrt()).powi(2);
        let (mut nearest2, mut stop) = (limit, stop_at(limit));
        for &(d1, d2) in nearby {
            if f64::from(i16::from(d1).pow(2) + i16::from(d2).pow(2)) >= stop {
                break;
            }
            let (w1, w2) = (c1 + i64::from(d1), c2 + i64::from(d2));
            let gap1 = ((v[0] - w1 as f64).abs() - 0.5).max(0.0);
            let gap2 = ((v[1] - w2 as f64).abs() - 0.5).max(0.0);
            let distance2 = gap1 * gap1 + gap2 * gap2;
            if distance2 < nearest2 {
                if distance2 == 0.0 {
                    return 0.0;
                }
                (nearest2, stop) = (distance2, stop_at(distance2));
            }
        }
        if nearest2 >= limit {
            1.0
        } else {
            let s = (0.5 * PI * nearest2.sqrt() / self.clearance).sin();
            s * s
        }
    }

    /// Number of nodes (drawn or not) the mask spans.
    pub(super) fn len(&self) -> usize {
        self.present.len()
    }

    /// Number of drawn dots.
    pub fn count(&self) -> usize {
        self.present.iter().filter(|&&r| r).count()
    }

    /// Image-frame point of the drawn nodes' mean `k̄` under `planes` (`φ_l = 2π·k̄_l`);
    /// `None` without drawn nodes or for singular planes.
    pub(super) fn centroid_at(&self, planes: &[PhasePlane; 2]) -> Option<Vector2<f64>> {
        let (mut sum, mut n) = (Vector2::zeros(), 0.0);
        for (index, _) in self.present.iter().enumerate().filter(|(_, &p)| p) {
            let (i, j) = (index / self.dims.1.max(1), index % self.dims.1.max(1));
            sum += Vector2::new(
                (self.first.0 + i as i64) as f64,
                (self.first.1 + j as i64) as f64,
            );
            n += 1.0;
        }
        let k = (n > 0.0).then_some(sum / n)?;
        let m = Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
        Some(m.try_inverse()? * Vector2::new(TAU * k.x - planes[0].c, TAU * k.y - planes[1].c))
    }
}

/// Row-major index of `(a, b)` in a grid whose entry `(0, 0)` is `first` and whose extent is
/// `dims`; `None` outside.
pub(super) fn grid_index(first: (i64, i64), dims: (usize, usize), a: i64, b: i64) -> Option<usize> {
    let (i, j) = (a - first.0, b - first.1);
    (i >= 0 && j >= 0 && (i as usize) < dims.0 && (j as usize) < dims.1)
        .then(|| i as usize * dims.1 + j as usize)
}

/// A mask's node weights for one sweep, padded by one node on every side so that a pixel's
/// four surrounding nodes are looked up without bounds checks per node: per node, `[1, w]` if
/// drawn (`w` its robust weight) and `[0, 0]` otherwise.
pub(super) struct NodeWeights {
    /// Node `(k₁, k₂)` of entry `(0, 0)`.
    pub(super) first: (i64, i64),
    /// Padded extent: nodes along `k₁` (rows of `entries`) and along `k₂`.
    pub(super) dims: (usize, usize),
    pub(super) entries: Vec<[f64; 2]>,
}

impl NodeWeights {
    /// The weights of `mask` with robust weights `nodes` (per mask node; empty: all 1).
    pub(super) fn new(mask: &NodeMask, nodes: &[f64]) -> Self {
        let dims = (mask.dims.0 + 2, mask.dims.1 + 2);
        let mut entries = vec![[0.0; 2]; dims.0 * dims.1];
        for i in 0..mask.dims.0 {
            for j in 0..mask.dims.1 {
                let index = i * mask.dims.1 + j;
                if mask.present[index] {
                    let robust = nodes.get(index).copied().unwrap_or(1.0);
                    entries[(i + 1) * dims.1 + j + 1] = [1.0, robust];
                }
            }
        }
        NodeWeights {
            first: (mask.first.0 - 1, mask.first.1 - 1),
            dims,
            entries,
        }
    }

    /// Layout weight of lattice coordinates `u` (see the module doc), in `[0, 1]`, and the same
    /// with each node's term multiplied by its robust weight: still a sum of node kernels, so
    /// the harmonics stay orthogonal under it. `cos_pi_u` is `cos πu` per axis.
    #[inline(always)]
    pub(super) fn weight(&self, u: [f64; 2], cos_pi_u: [f64; 2]) -> (f64, f64) {
        let (k1, k2) = (u[0].floor() as i64, u[1].floor() as i64);
        let (i, j) = (k1 - self.first.0, k2 - self.first.1);
        // Outside the padded table all four nodes are outside the mask.
        if i < 0 || j < 0 || i as usize + 1 >= self.dims.0 || j as usize + 1 >= self.dims.1 {
            return (0.0, 0.0);
        }
        let base = i as usize * self.dims.1 + j as usize;
        let node = |offset: usize| self.entries.get(base + offset).copied().unwrap_or([0.0; 2]);
        let (e00, e01) = (node(0), node(1));
        let (e10, e11) = (node(self.dims.1), node(self.dims.1 + 1));
        // b(t) = cos²(πt/2) = (1 + cos πt)/2 at t = u − k, cos πt = (−1)^k·cos πu.
        let partition = |k: i64, c: f64| {
            let b = 0.5 + 0.5 * if k % 2 == 0 { c } else { -c };
            [b, 1.0 - b]
        };
        let (b1, b2) = (partition(k1, cos_pi_u[0]), partition(k2, cos_pi_u[1]));
        let sum = |m: usize| {
            b1[0] * (b2[0] * e00[m] + b2[1] * e01[m]) + b1[1] * (b2[0] * e10[m] + b2[1] * e11[m])
        };
        (sum(0), sum(1))
    }
}
