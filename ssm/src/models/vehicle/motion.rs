//! The deterministic motion model of SPEC §3: the exact step (cubic yaw kept, positions
//! by Gauss–Legendre quadrature) as a single step, a batched struct-of-arrays kernel
//! generic over [`Float`], and a differentiable version on the tape; plus the paper's
//! closed form (cubic yaw term dropped, Fresnel integrals) and an adaptive reference
//! integrator, both in f64 for comparison and validation.
//!
//! With the action held constant over `s in [0, dt]`:
//!
//! ```text
//! v(s)     = v0 + accel s
//! kappa(s) = kappa0 + pinch s
//! yaw(s)   = yaw0 + d(s),  d(s) = v0 kappa0 s + (v0 pinch + accel kappa0) s^2/2 + accel pinch s^3/3
//! x(dt)    = x0 + int_0^dt v(s) cos yaw(s) ds,   y(dt) = y0 + int_0^dt v(s) sin yaw(s) ds
//! ```
//!
//! The integral is evaluated in the frame of the initial heading,
//! `L = int v(s) (cos d(s), sin d(s)) ds`, then rotated by `yaw0`: the same number,
//! but the trigonometric arguments stay small (|d| is a few radians at most), which
//! keeps f32 accurate and suits fast polynomial sin/cos kernels.

use std::f64::consts::PI;
use std::fmt;

use autodiff::{Float, Tensor};
use serde::{Deserialize, Serialize};

use super::state::{Action, ActionVars, ActionsRef, StateVars, StatesMut, StatesRef, VehicleState};

/// The step length of the data (s): observations arrive at 3 Hz.
pub const DEFAULT_DT: f64 = 1.0 / 3.0;

/// Largest Gauss–Legendre rule on offer.
const MAX_NODES: usize = 16;
/// Objects advanced together by the batched kernel: one AVX2 vector of f32.
const LANES: usize = 8;

/// A Gauss–Legendre rule for the position integral.
///
/// Measured over the data's range (speeds 0–40 m/s, |kappa| <= 0.2 1/m,
/// |accel| <= 5 m/s^2, |pinch| <= 0.3 1/(m s), dt = 1/3 s), against an adaptive
/// reference: 8 nodes are within 1e-6 m (see `tests/vehicle_motion.rs`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Quadrature {
    /// 4 nodes: exact for polynomials of degree 7.
    Gl4,
    /// 8 nodes (default): exact for polynomials of degree 15.
    #[default]
    Gl8,
    /// 16 nodes: exact for polynomials of degree 31.
    Gl16,
}

impl Quadrature {
    /// Every rule on offer.
    pub const ALL: [Quadrature; 3] = [Quadrature::Gl4, Quadrature::Gl8, Quadrature::Gl16];

    /// Number of nodes.
    pub fn nodes(self) -> usize {
        match self {
            Quadrature::Gl4 => 4,
            Quadrature::Gl8 => 8,
            Quadrature::Gl16 => 16,
        }
    }

    /// The rule with `n` nodes, if on offer.
    pub fn from_nodes(n: usize) -> Option<Self> {
        Self::ALL.into_iter().find(|q| q.nodes() == n)
    }
}

/// The `n`-point Gauss–Legendre rule on `[-1, 1]`: nodes (ascending) and weights,
/// computed by Newton's method on the Legendre polynomial to full f64 precision.
///
/// ```
/// let (x, w) = ssm::models::vehicle::motion::gauss_legendre(3);
/// assert!((x[2] - (0.6f64).sqrt()).abs() < 1e-15);
/// assert!((w[1] - 8.0 / 9.0).abs() < 1e-15);
/// ```
pub fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    assert!(n >= 1, "gauss_legendre: need at least one node");
    // P_n(x) and P_n'(x) by the three-term recurrence.
    let legendre = |x: f64| -> (f64, f64) {
        let (mut p0, mut p1) = (1.0, x);
        for k in 2..=n {
            let kf = k as f64;
            let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
            p0 = p1;
            p1 = p2;
        }
        if n == 1 {
            return (x, 1.0);
        }
        (p1, n as f64 * (x * p1 - p0) / (x * x - 1.0))
    };
    let mut nodes = vec![0.0; n];
    let mut weights = vec![0.0; n];
    for i in 0..n.div_ceil(2) {
        // Tricomi's initial guess for the i-th largest root, then Newton.
        let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        for _ in 0..100 {
            let (p, dp) = legendre(x);
            let dx = p / dp;
            x -= dx;
            if dx.abs() <= 1e-16 {
                break;
            }
        }
        let (_, dp) = legendre(x);
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        nodes[n - 1 - i] = x;
        nodes[i] = -x;
        weights[n - 1 - i] = w;
        weights[i] = w;
    }
    if n % 2 == 1 {
        nodes[n / 2] = 0.0;
    }
    (nodes, weights)
}

/// Why a motion model could not be built.
#[derive(Clone, Debug, PartialEq)]
pub enum MotionError {
    /// The step length must be finite and positive.
    InvalidDt(f64),
}

impl fmt::Display for MotionError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MotionError::InvalidDt(dt) => {
                write!(f, "motion model: step length dt = {dt} must be finite and > 0")
            }
        }
    }
}

impl std::error::Error for MotionError {}

/// The exact motion model: cubic yaw, positions by Gauss–Legendre quadrature.
///
/// ```
/// use ssm::models::vehicle::{Action, MotionModel, VehicleState};
/// let m = MotionModel::default();
/// // Straight line, accelerating: x = v0 dt + accel dt^2 / 2.
/// let s = m.step(&VehicleState::new(0.0f64, 0.0, 0.0, 10.0, 0.0), &Action::new(3.0, 0.0));
/// let dt = 1.0 / 3.0;
/// assert!((s.x - (10.0 * dt + 1.5 * dt * dt)).abs() < 1e-12);
/// assert!((s.v - 11.0).abs() < 1e-12);
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct MotionModel {
    dt: f64,
    quadrature: Quadrature,
    /// Nodes mapped to `[0, dt]` (first `quadrature.nodes()` entries used).
    s: [f64; MAX_NODES],
    /// Weights scaled to `[0, dt]`.
    w: [f64; MAX_NODES],
}

impl Default for MotionModel {
    fn default() -> Self {
        Self::new(DEFAULT_DT, Quadrature::default()).expect("default dt is valid")
    }
}

/// A quadrature rule in the working precision, sized at compile time so the node
/// loop unrolls inside the per-object loop.
struct Rule<F, const N: usize> {
    s: [F; N],
    w: [F; N],
    dt: F,
}

impl MotionModel {
    /// A model with step length `dt` (s) and the given quadrature rule.
    pub fn new(dt: f64, quadrature: Quadrature) -> Result<Self, MotionError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(MotionError::InvalidDt(dt));
        }
        let n = quadrature.nodes();
        let (x, wx) = gauss_legendre(n);
        let mut s = [0.0; MAX_NODES];
        let mut w = [0.0; MAX_NODES];
        for i in 0..n {
            s[i] = 0.5 * dt * (1.0 + x[i]);
            w[i] = 0.5 * dt * wx[i];
        }
        Ok(MotionModel { dt, quadrature, s, w })
    }

    /// The step length (s).
    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// The quadrature rule.
    pub fn quadrature(&self) -> Quadrature {
        self.quadrature
    }

    fn rule<F: Float, const N: usize>(&self) -> Rule<F, N> {
        debug_assert_eq!(N, self.quadrature.nodes());
        Rule {
            s: std::array::from_fn(|i| F::from_f64(self.s[i])),
            w: std::array::from_fn(|i| F::from_f64(self.w[i])),
            dt: F::from_f64(self.dt),
        }
    }

    /// One object's next state.
    pub fn step<F: Float>(&self, s: &VehicleState<F>, a: &Action<F>) -> VehicleState<F> {
        let (s, a) = ([s.x, s.y, s.yaw, s.v, s.kappa].map(|c| [c]), [a.accel, a.pinch].map(|c| [c]));
        let r = match self.quadrature {
            Quadrature::Gl4 => advance(&self.rule::<F, 4>(), &s, &a),
            Quadrature::Gl8 => advance(&self.rule::<F, 8>(), &s, &a),
            Quadrature::Gl16 => advance(&self.rule::<F, 16>(), &s, &a),
        };
        VehicleState::new(r[0][0], r[1][0], r[2][0], r[3][0], r[4][0])
    }

    /// Advances every state in place by one step under its action.
    ///
    /// A plain loop over the objects with the node loop unrolled inside; no
    /// allocation. Panics if the lengths differ.
    #[track_caller]
    pub fn propagate_in_place<F: Float>(&self, states: StatesMut<'_, F>, actions: ActionsRef<'_, F>) {
        self.dispatch(None, states, actions);
    }

    /// Writes the next state of every `from[i]` under `actions[i]` into `to[i]`.
    /// Panics if the lengths differ.
    #[track_caller]
    pub fn propagate<F: Float>(&self, from: StatesRef<'_, F>, actions: ActionsRef<'_, F>, to: StatesMut<'_, F>) {
        let n = from.len();
        assert_eq!(n, to.len(), "MotionModel::propagate: {n} states in, room for {} out", to.len());
        self.dispatch(Some(from), to, actions);
    }

    /// [`Self::run`] for the model's rule.
    #[track_caller]
    fn dispatch<F: Float>(&self, from: Option<StatesRef<'_, F>>, to: StatesMut<'_, F>, actions: ActionsRef<'_, F>) {
        match self.quadrature {
            Quadrature::Gl4 => self.run::<F, 4>(from, to, actions),
            Quadrature::Gl8 => self.run::<F, 8>(from, to, actions),
            Quadrature::Gl16 => self.run::<F, 16>(from, to, actions),
        }
    }

    /// Advances the states `from` (or `st` itself, in place) into `st`.
    #[track_caller]
    fn run<F: Float, const N: usize>(
        &self,
        from: Option<StatesRef<'_, F>>,
        st: StatesMut<'_, F>,
        actions: ActionsRef<'_, F>,
    ) {
        let n = st.len();
        assert_eq!(n, actions.len(), "MotionModel::propagate: {n} states but {} actions", actions.len());
        let rule = self.rule::<F, N>();
        let mut cols: [&mut [F]; 5] = [st.x, st.y, st.yaw, st.v, st.kappa];
        let (acc, pin) = (&actions.accel[..n], &actions.pinch[..n]);
        // Whole groups of `LANES` objects: the fixed-size lane loop compiles to SIMD
        // (a plain loop over the objects stays scalar: its body is too large for the
        // loop vectoriser). The remainder goes through the same group, padded.
        let mut start = 0;
        while start < n {
            let m = LANES.min(n - start);
            let load = |c: &[F]| -> [F; LANES] { std::array::from_fn(|l| if l < m { c[start + l] } else { F::ZERO }) };
            let state = match &from {
                Some(f) => [f.x, f.y, f.yaw, f.v, f.kappa].map(|c| load(&c[..n])),
                None => [0, 1, 2, 3, 4].map(|j| load(&cols[j][..n])),
            };
            let next = advance(&rule, &state, &[load(acc), load(pin)]);
            for (col, new) in cols.iter_mut().zip(&next) {
                col[start..start + m].copy_from_slice(&new[..m]);
            }
            start += m;
        }
    }

    /// The same step on a tape, differentiable in every state and action component.
    ///
    /// All inputs have shape `[n]`; so do the outputs. Each output is one fused
    /// node ([`autodiff::Tape::precomputed`]) whose values are those of
    /// [`MotionModel::propagate`] (the same arithmetic) and whose partial derivatives
    /// come out of the same passes over the quadrature nodes (`step_tile`).
    #[track_caller]
    pub fn propagate_on_tape<'t, F: Float>(&self, s: &StateVars<'t, F>, a: &ActionVars<'t, F>) -> StateVars<'t, F> {
        let n = s.x.numel();
        for (name, v) in [
            ("x", s.x),
            ("y", s.y),
            ("yaw", s.yaw),
            ("v", s.v),
            ("kappa", s.kappa),
            ("accel", a.accel),
            ("pinch", a.pinch),
        ] {
            assert_eq!(
                v.shape(),
                [n],
                "MotionModel::propagate_on_tape: {name} has shape {:?}, expected [{n}]",
                v.shape()
            );
        }
        match self.quadrature {
            Quadrature::Gl4 => self.tape_step::<F, 4>(s, a),
            Quadrature::Gl8 => self.tape_step::<F, 8>(s, a),
            Quadrature::Gl16 => self.tape_step::<F, 16>(s, a),
        }
    }

    /// [`MotionModel::propagate_on_tape`] with an `N`-node rule.
    fn tape_step<'t, F: Float, const N: usize>(&self, s: &StateVars<'t, F>, a: &ActionVars<'t, F>) -> StateVars<'t, F> {
        let n = s.x.numel();
        let rule = self.rule::<F, N>();
        let tape = s.x.tape();
        // Every element is written by `step_tile`.
        let mut next: [Vec<F>; 5] = std::array::from_fn(|_| tape.buffer(n));
        let mut partials: [Vec<F>; STEP_PARTIALS] = std::array::from_fn(|_| tape.buffer(n));
        {
            let inputs = [s.x, s.y, s.yaw, s.v, s.kappa, a.accel, a.pinch].map(|v| v.value());
            let inputs = inputs.each_ref().map(|v| &v.data()[..n]);
            let mut start = 0;
            while start < n {
                let rows = start..(start + TAPE_TILE).min(n);
                step_tile(
                    &rule,
                    inputs.map(|v| &v[rows.clone()]),
                    next.each_mut().map(|c| &mut c[rows.clone()]),
                    partials.each_mut().map(|c| &mut c[rows.clone()]),
                );
                start = rows.end;
            }
        }
        let full = |v: F| {
            let mut b = tape.buffer(n);
            b.fill(v);
            Tensor::from_vec(b)
        };
        let ones = || full(F::ONE);
        let dt = || full(F::from_f64(self.dt));
        let [x1, y1, yaw1, v1, k1] = next.map(Tensor::from_vec);
        let [dx_yaw, dx_v, dx_k, dx_a, dx_p, dy_yaw, dy_v, dy_k, dy_a, dy_p, dyaw_v, dyaw_k, dyaw_a, dyaw_p] =
            partials.map(Tensor::from_vec);
        StateVars {
            x: tape.precomputed(
                x1,
                vec![(s.x, ones()), (s.yaw, dx_yaw), (s.v, dx_v), (s.kappa, dx_k), (a.accel, dx_a), (a.pinch, dx_p)],
            ),
            y: tape.precomputed(
                y1,
                vec![(s.y, ones()), (s.yaw, dy_yaw), (s.v, dy_v), (s.kappa, dy_k), (a.accel, dy_a), (a.pinch, dy_p)],
            ),
            yaw: tape.precomputed(
                yaw1,
                vec![(s.yaw, ones()), (s.v, dyaw_v), (s.kappa, dyaw_k), (a.accel, dyaw_a), (a.pinch, dyaw_p)],
            ),
            v: tape.precomputed(v1, vec![(s.v, ones()), (a.accel, dt())]),
            kappa: tape.precomputed(k1, vec![(s.kappa, ones()), (a.pinch, dt())]),
        }
    }
}

/// Partial derivatives [`step_tile`] returns: of the next `x` and `y` with respect
/// to `(yaw, v, kappa, accel, pinch)`, then of the next yaw with respect to `(v,
/// kappa, accel, pinch)`. (The rest are 0, 1 or `dt`.)
const STEP_PARTIALS: usize = 14;

/// Objects per tile of [`step_tile`]: its per-object accumulators stay in L1.
const TAPE_TILE: usize = 256;

/// [`advance`] for a tile of at most [`TAPE_TILE`] objects (inputs `(x, y, yaw, v,
/// kappa, accel, pinch)`), with the partial derivatives of the next state (the
/// order of [`STEP_PARTIALS`]). The values are computed by the same expressions in
/// the same order as [`advance`], so they are equal; the loops run over objects
/// innermost (one pass per quadrature node), which lets them vectorise.
///
/// With `d(s) = c1 s + c2 s^2 + c3 s^3` and `L = sum_i w_i (v + accel s_i) (cos d_i,
/// sin d_i)`, a parameter `p` of `(v, kappa, accel, pinch)` moves `L` by
/// `sum_i w_i [d(v + accel s_i)/dp (cos, sin) + (v + accel s_i) dd_i/dp (-sin, cos)]`,
/// and the next position is the start plus `L` rotated by the heading.
#[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
fn step_tile<F: Float, const N: usize>(
    rule: &Rule<F, N>,
    inputs: [&[F]; 7],
    next: [&mut [F]; 5],
    partials: [&mut [F]; STEP_PARTIALS],
) {
    let m = inputs[0].len();
    assert!(m <= TAPE_TILE, "step_tile: {m} objects in a tile of {TAPE_TILE}");
    let (half, third) = (F::from_f64(0.5), F::from_f64(1.0 / 3.0));
    let [xs, ys, yaws, vs, ks, acc, pin] = inputs.map(|v| &v[..m]);
    let (mut c1, mut c2, mut c3) = ([F::ZERO; TAPE_TILE], [F::ZERO; TAPE_TILE], [F::ZERO; TAPE_TILE]);
    for i in 0..m {
        c1[i] = vs[i] * ks[i];
        c2[i] = (vs[i] * pin[i] + acc[i] * ks[i]) * half;
        c3[i] = (acc[i] * pin[i]) * third;
    }
    let (c1, c2, c3) = (&c1[..m], &c2[..m], &c3[..m]);
    // L and d L / d (v, kappa, accel, pinch).
    let (mut lx, mut ly) = ([F::ZERO; TAPE_TILE], [F::ZERO; TAPE_TILE]);
    let (mut gx, mut gy) = ([[F::ZERO; TAPE_TILE]; 4], [[F::ZERO; TAPE_TILE]; 4]);
    for j in 0..N {
        let (si, wi) = (rule.s[j], rule.w[j]);
        let (s2, s3, wsi) = (si * si * half, si * si * si * third, wi * si);
        let (lx, ly) = (&mut lx[..m], &mut ly[..m]);
        let [gx0, gx1, gx2, gx3] = gx.each_mut().map(|g| &mut g[..m]);
        let [gy0, gy1, gy2, gy3] = gy.each_mut().map(|g| &mut g[..m]);
        for i in 0..m {
            let d = ((c3[i] * si + c2[i]) * si + c1[i]) * si;
            let wv = wi * (vs[i] + acc[i] * si);
            let (cd, sd) = (d.cos(), d.sin());
            lx[i] += wv * cd;
            ly[i] += wv * sd;
            let (ws, wc) = (wv * sd, wv * cd);
            // d d_i / d (v, kappa, accel, pinch).
            let dd = [
                ks[i] * si + pin[i] * s2,
                vs[i] * si + acc[i] * s2,
                ks[i] * s2 + pin[i] * s3,
                vs[i] * s2 + acc[i] * s3,
            ];
            gx0[i] += wi * cd - ws * dd[0];
            gy0[i] += wi * sd + wc * dd[0];
            gx1[i] += -ws * dd[1];
            gy1[i] += wc * dd[1];
            gx2[i] += wsi * cd - ws * dd[2];
            gy2[i] += wsi * sd + wc * dd[2];
            gx3[i] += -ws * dd[3];
            gy3[i] += wc * dd[3];
        }
    }
    let (mut cy, mut sy) = ([F::ZERO; TAPE_TILE], [F::ZERO; TAPE_TILE]);
    for i in 0..m {
        cy[i] = yaws[i].cos();
        sy[i] = yaws[i].sin();
    }
    let (cy, sy, lx, ly) = (&cy[..m], &sy[..m], &lx[..m], &ly[..m]);
    let t = rule.dt;
    let (t2, t3) = (t * t * half, t * t * t * third);
    let [nx, ny, nyaw, nv, nk] = next.map(|c| &mut c[..m]);
    for i in 0..m {
        nx[i] = xs[i] + (cy[i] * lx[i] - sy[i] * ly[i]);
        ny[i] = ys[i] + (sy[i] * lx[i] + cy[i] * ly[i]);
        nyaw[i] = yaws[i] + ((c3[i] * t + c2[i]) * t + c1[i]) * t;
        nv[i] = vs[i] + acc[i] * t;
        nk[i] = ks[i] + pin[i] * t;
    }
    let [px_yaw, px_v, px_k, px_a, px_p, py_yaw, py_v, py_k, py_a, py_p, pyaw_v, pyaw_k, pyaw_a, pyaw_p] =
        partials.map(|c| &mut c[..m]);
    let [gx0, gx1, gx2, gx3] = gx.each_ref().map(|g| &g[..m]);
    let [gy0, gy1, gy2, gy3] = gy.each_ref().map(|g| &g[..m]);
    // Separate passes: one loop with all 14 outputs does not vectorise.
    for i in 0..m {
        px_yaw[i] = -sy[i] * lx[i] - cy[i] * ly[i];
        px_v[i] = cy[i] * gx0[i] - sy[i] * gy0[i];
        px_k[i] = cy[i] * gx1[i] - sy[i] * gy1[i];
        px_a[i] = cy[i] * gx2[i] - sy[i] * gy2[i];
        px_p[i] = cy[i] * gx3[i] - sy[i] * gy3[i];
    }
    for i in 0..m {
        py_yaw[i] = cy[i] * lx[i] - sy[i] * ly[i];
        py_v[i] = sy[i] * gx0[i] + cy[i] * gy0[i];
        py_k[i] = sy[i] * gx1[i] + cy[i] * gy1[i];
        py_a[i] = sy[i] * gx2[i] + cy[i] * gy2[i];
        py_p[i] = sy[i] * gx3[i] + cy[i] * gy3[i];
    }
    for i in 0..m {
        pyaw_v[i] = ks[i] * t + pin[i] * t2;
        pyaw_k[i] = vs[i] * t + acc[i] * t2;
        pyaw_a[i] = ks[i] * t2 + pin[i] * t3;
        pyaw_p[i] = vs[i] * t2 + acc[i] * t3;
    }
}

/// The exact step for `L` objects with an `N`-node rule: `s` holds the states'
/// components `(x, y, yaw, v, kappa)` and `a` the actions' `(accel, pinch)`, one
/// lane per object; returns the next states' components. Every lane computes the
/// same operations in the same order whatever `L` is, so a single step (`L = 1`)
/// and a batch agree bitwise; the loops over lanes are innermost so that a batch
/// of `L = LANES` compiles to SIMD across objects.
#[inline(always)]
fn advance<F: Float, const N: usize, const L: usize>(r: &Rule<F, N>, s: &[[F; L]; 5], a: &[[F; L]; 2]) -> [[F; L]; 5] {
    let half = F::from_f64(0.5);
    let third = F::from_f64(1.0 / 3.0);
    let [x, y, yaw, v, kappa] = s;
    let [accel, pinch] = a;
    // yaw(s) - yaw0 = ((c3 s + c2) s + c1) s
    let c1: [F; L] = std::array::from_fn(|l| v[l] * kappa[l]);
    let c2: [F; L] = std::array::from_fn(|l| (v[l] * pinch[l] + accel[l] * kappa[l]) * half);
    let c3: [F; L] = std::array::from_fn(|l| (accel[l] * pinch[l]) * third);
    let (mut lx, mut ly) = ([F::ZERO; L], [F::ZERO; L]);
    for i in 0..N {
        let si = r.s[i];
        for l in 0..L {
            let d = ((c3[l] * si + c2[l]) * si + c1[l]) * si;
            let wv = r.w[i] * (v[l] + accel[l] * si);
            lx[l] += wv * d.cos();
            ly[l] += wv * d.sin();
        }
    }
    let t = r.dt;
    let mut out = [[F::ZERO; L]; 5];
    for l in 0..L {
        let (cy, sy) = (yaw[l].cos(), yaw[l].sin());
        out[0][l] = x[l] + (cy * lx[l] - sy * ly[l]);
        out[1][l] = y[l] + (sy * lx[l] + cy * ly[l]);
        out[2][l] = yaw[l] + ((c3[l] * t + c2[l]) * t + c1[l]) * t;
        out[3][l] = v[l] + accel[l] * t;
        out[4][l] = kappa[l] + pinch[l] * t;
    }
    out
}

/// Which yaw profile a position integral follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum YawProfile {
    /// The exact cubic `yaw(s)` (the project's model).
    Exact,
    /// The paper's approximation: the `accel pinch s^3 / 3` term dropped.
    DropCubic,
}

/// Tolerance of the reference integrator (absolute, m).
const REFERENCE_TOL: f64 = 1e-13;
/// Deepest bisection of the reference integrator.
const REFERENCE_MAX_DEPTH: u32 = 40;

/// A slow, high-accuracy step for validation: the position integral by adaptive
/// Simpson quadrature (absolute tolerance 1e-13 m) in the world frame, with the
/// chosen yaw profile for the positions; yaw, speed and curvature are exact.
pub fn reference_step(dt: f64, s: &VehicleState<f64>, a: &Action<f64>, profile: YawProfile) -> VehicleState<f64> {
    let cubic = match profile {
        YawProfile::Exact => a.accel * a.pinch / 3.0,
        YawProfile::DropCubic => 0.0,
    };
    let c1 = s.v * s.kappa;
    let c2 = 0.5 * (s.v * a.pinch + a.accel * s.kappa);
    let f = |u: f64| -> [f64; 2] {
        let yaw = s.yaw + c1 * u + c2 * u * u + cubic * u * u * u;
        let v = s.v + a.accel * u;
        [v * yaw.cos(), v * yaw.sin()]
    };
    let (fa, fm, fb) = (f(0.0), f(0.5 * dt), f(dt));
    let whole = simpson(dt, fa, fm, fb);
    let [ix, iy] = adaptive_simpson(&f, 0.0, dt, fa, fm, fb, whole, REFERENCE_TOL, 0);
    VehicleState::new(
        s.x + ix,
        s.y + iy,
        s.yaw + c1 * dt + c2 * dt * dt + a.accel * a.pinch * dt * dt * dt / 3.0,
        s.v + a.accel * dt,
        s.kappa + a.pinch * dt,
    )
}

fn simpson(h: f64, fa: [f64; 2], fm: [f64; 2], fb: [f64; 2]) -> [f64; 2] {
    [0, 1].map(|k| h / 6.0 * (fa[k] + 4.0 * fm[k] + fb[k]))
}

#[allow(clippy::too_many_arguments)]
fn adaptive_simpson(
    f: &impl Fn(f64) -> [f64; 2],
    a: f64,
    b: f64,
    fa: [f64; 2],
    fm: [f64; 2],
    fb: [f64; 2],
    whole: [f64; 2],
    tol: f64,
    depth: u32,
) -> [f64; 2] {
    let m = 0.5 * (a + b);
    let (flm, frm) = (f(0.5 * (a + m)), f(0.5 * (m + b)));
    let left = simpson(m - a, fa, flm, fm);
    let right = simpson(b - m, fm, frm, fb);
    let err = [0, 1].map(|k| left[k] + right[k] - whole[k]);
    if depth >= REFERENCE_MAX_DEPTH || err[0].abs().max(err[1].abs()) <= 15.0 * tol {
        // Richardson extrapolation of the two Simpson estimates.
        return [0, 1].map(|k| left[k] + right[k] + err[k] / 15.0);
    }
    let l = adaptive_simpson(f, a, m, fa, flm, fm, left, 0.5 * tol, depth + 1);
    let r = adaptive_simpson(f, m, b, fm, frm, fb, right, 0.5 * tol, depth + 1);
    [l[0] + r[0], l[1] + r[1]]
}

/// The paper's closed form: positions integrated with the cubic yaw term dropped
/// (`yaw(s)` quadratic), which Fresnel integrals solve exactly; yaw, speed and
/// curvature follow the exact model. For comparison only (f64, one object).
///
/// When `|c| dt^2 <= 1`, with `c = (v0 pinch + accel kappa0) / 2` the quadratic
/// yaw coefficient, the Fresnel expression cancels catastrophically (its terms grow
/// like `1/c`), so the same integral is summed as a power series in `c` instead;
/// both branches agree with direct quadrature of the quadratic-yaw integrand to
/// about 1e-12 m while the heading swept by `v0 kappa0 dt` stays below ~10 rad.
///
/// ```
/// use ssm::models::vehicle::motion::closed_form_step;
/// use ssm::models::vehicle::{Action, VehicleState};
/// // Without pinch or acceleration the cubic term vanishes: a circular arc.
/// let (k, v, dt) = (0.1, 10.0, 1.0 / 3.0);
/// let s = closed_form_step(dt, &VehicleState::new(0.0, 0.0, 0.0, v, k), &Action::new(0.0, 0.0));
/// assert!((s.x - (v * k * dt).sin() / k).abs() < 1e-12);
/// ```
pub fn closed_form_step(dt: f64, s: &VehicleState<f64>, a: &Action<f64>) -> VehicleState<f64> {
    let b = s.v * s.kappa;
    let c = 0.5 * (s.v * a.pinch + a.accel * s.kappa);
    let local = if c.abs() * dt * dt <= 1.0 {
        quadratic_phase_series(dt, s.v, a.accel, b, c)
    } else {
        quadratic_phase_fresnel(dt, s.v, a.accel, b, c)
    };
    let (cy, sy) = (s.yaw.cos(), s.yaw.sin());
    VehicleState::new(
        s.x + cy * local.re - sy * local.im,
        s.y + sy * local.re + cy * local.im,
        s.yaw + b * dt + c * dt * dt + a.accel * a.pinch * dt * dt * dt / 3.0,
        s.v + a.accel * dt,
        s.kappa + a.pinch * dt,
    )
}

/// A minimal complex number for the closed form.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Complex {
    re: f64,
    im: f64,
}

impl Complex {
    const fn new(re: f64, im: f64) -> Self {
        Complex { re, im }
    }
    fn cis(t: f64) -> Self {
        Complex::new(t.cos(), t.sin())
    }
    fn add(self, o: Complex) -> Complex {
        Complex::new(self.re + o.re, self.im + o.im)
    }
    fn sub(self, o: Complex) -> Complex {
        Complex::new(self.re - o.re, self.im - o.im)
    }
    fn mul(self, o: Complex) -> Complex {
        Complex::new(self.re * o.re - self.im * o.im, self.re * o.im + self.im * o.re)
    }
    fn scale(self, k: f64) -> Complex {
        Complex::new(self.re * k, self.im * k)
    }
    fn inv(self) -> Complex {
        let d = self.re * self.re + self.im * self.im;
        Complex::new(self.re / d, -self.im / d)
    }
    fn norm1(self) -> f64 {
        self.re.abs() + self.im.abs()
    }
}

/// Series terms stop below this fraction of the running sum.
const SERIES_EPS: f64 = 1e-18;

/// `int_0^T (v0 + acc u) e^{i (b u + c u^2)} du` as a power series in `c`:
/// `sum_k (i c T^2)^k / k! (v0 T e_{2k} + acc T^2 e_{2k+1})` with
/// `e_n = sum_j (i b T)^j / (j! (n + j + 1))`. Needs `|c| T^2 <= 1`.
fn quadratic_phase_series(t: f64, v0: f64, acc: f64, b: f64, c: f64) -> Complex {
    let ibt = Complex::new(0.0, b * t);
    let e = |n: usize| -> Complex {
        let mut term = Complex::new(1.0, 0.0); // (ibT)^j / j!
        let mut sum = Complex::new(0.0, 0.0);
        for j in 0..400 {
            let add = term.scale(1.0 / (n + j + 1) as f64);
            sum = sum.add(add);
            if j as f64 > (b * t).abs() && term.norm1() <= SERIES_EPS * sum.norm1() {
                break;
            }
            term = term.mul(ibt).scale(1.0 / (j + 1) as f64);
        }
        sum
    };
    let ict2 = Complex::new(0.0, c * t * t);
    // |e_n| <= e^{|bT|} / (n + 1): a bound on every later term, so the sum stops on
    // the bound (a single term can vanish by cancellation before the series has).
    let scale = (v0.abs() * t + acc.abs() * t * t) * (b * t).abs().exp();
    let mut factor = Complex::new(1.0, 0.0); // (icT^2)^k / k!
    let mut sum = Complex::new(0.0, 0.0);
    for k in 0..60 {
        let inner = e(2 * k).scale(v0 * t).add(e(2 * k + 1).scale(acc * t * t));
        sum = sum.add(factor.mul(inner));
        factor = factor.mul(ict2).scale(1.0 / (k + 1) as f64);
        if factor.norm1() * scale <= SERIES_EPS * sum.norm1() {
            break;
        }
    }
    sum
}

/// The same integral by completing the square (needs `c != 0`; well conditioned
/// for `|c| T^2 > 1`): with `v0 + acc u = acc/(2c) (b + 2cu) + (v0 - acc b/(2c))`,
/// the first part integrates to `-i acc/(2c) (e^{i phase(T)} - 1)` and the second
/// is a difference of Fresnel integrals.
fn quadratic_phase_fresnel(t: f64, v0: f64, acc: f64, b: f64, c: f64) -> Complex {
    let sigma = c.signum();
    let k = (2.0 * c.abs() / PI).sqrt();
    let shift = b / (2.0 * c);
    let (c0, s0) = fresnel(shift * k);
    let (c1, s1) = fresnel((t + shift) * k);
    let j = Complex::cis(-b * b / (4.0 * c)).mul(Complex::new(c1 - c0, sigma * (s1 - s0)).scale(1.0 / k));
    let exact_part =
        Complex::cis(b * t + c * t * t).sub(Complex::new(1.0, 0.0)).mul(Complex::new(0.0, -acc / (2.0 * c)));
    exact_part.add(j.scale(v0 - acc * shift))
}

/// Fresnel integrals `(C(x), S(x)) = int_0^x (cos, sin)(pi t^2 / 2) dt`: the power
/// series for `|x| <= 1.5`, else the continued fraction of the complementary error
/// function (modified Lentz), both to about 1e-15.
fn fresnel(x: f64) -> (f64, f64) {
    const SERIES_MAX: f64 = 1.5;
    const TINY: f64 = 1e-300;
    let ax = x.abs();
    let (c, s) = if ax < 1e-150 {
        (ax, 0.0)
    } else if ax <= SERIES_MAX {
        // C = sum_n (-1)^n (pi/2)^{2n} x^{4n+1} / ((2n)! (4n+1)),
        // S = sum_n (-1)^n (pi/2)^{2n+1} x^{4n+3} / ((2n+1)! (4n+3)).
        let t = 0.5 * PI * ax * ax;
        let (mut c, mut s) = (0.0, 0.0);
        let mut term = ax; // ax t^m / m!
        for m in 0..100 {
            let contrib = term / (2 * m + 1) as f64;
            let sign = if (m / 2) % 2 == 0 { 1.0 } else { -1.0 };
            if m % 2 == 0 {
                c += sign * contrib;
            } else {
                s += sign * contrib;
            }
            if contrib < 1e-18 * c.abs().max(s.abs()).max(TINY) {
                break;
            }
            term *= t / (m + 1) as f64;
        }
        (c, s)
    } else {
        let mut b = Complex::new(1.0, -PI * ax * ax);
        let mut cc = Complex::new(1.0 / TINY, 0.0);
        let mut d = b.inv();
        let mut h = d;
        let mut n = -1.0;
        for _ in 2..1000 {
            n += 2.0;
            let a = -n * (n + 1.0);
            b = b.add(Complex::new(4.0, 0.0));
            d = d.scale(a).add(b).inv();
            cc = b.add(cc.inv().scale(a));
            let del = cc.mul(d);
            h = h.mul(del);
            if (del.re - 1.0).abs() + del.im.abs() < 1e-16 {
                break;
            }
        }
        h = Complex::new(ax, -ax).mul(h);
        let cs = Complex::new(0.5, 0.5).mul(Complex::new(1.0, 0.0).sub(Complex::cis(0.5 * PI * ax * ax).mul(h)));
        (cs.re, cs.im)
    };
    if x < 0.0 {
        (-c, -s)
    } else {
        (c, s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Composite Gauss–Legendre of `(cos, sin)(pi t^2/2)` on `[0, x]`: an independent
    /// check of the Fresnel implementation.
    fn fresnel_quadrature(x: f64) -> (f64, f64) {
        let (nodes, weights) = gauss_legendre(20);
        let panels = 200;
        let h = x / panels as f64;
        let (mut c, mut s) = (0.0, 0.0);
        for p in 0..panels {
            let a = p as f64 * h;
            for (xi, wi) in nodes.iter().zip(&weights) {
                let t = a + 0.5 * h * (1.0 + xi);
                let ph = 0.5 * PI * t * t;
                c += 0.5 * h * wi * ph.cos();
                s += 0.5 * h * wi * ph.sin();
            }
        }
        (c, s)
    }

    #[test]
    fn fresnel_matches_quadrature_on_both_branches() {
        for &x in &[0.0, 1e-3, 0.3, 1.0, 1.49, 1.5, 1.51, 2.0, 3.7, 7.5, 12.0, 30.0, -0.8, -4.2] {
            let (c, s) = fresnel(x);
            let (cq, sq) = fresnel_quadrature(x);
            assert!(
                (c - cq).abs() < 1e-13 && (s - sq).abs() < 1e-13,
                "fresnel({x}) = ({c}, {s}), quadrature ({cq}, {sq})"
            );
        }
        // Limits at infinity.
        let (c, s) = fresnel(1e6);
        assert!((c - 0.5).abs() < 1e-6 && (s - 0.5).abs() < 1e-6);
    }

    #[test]
    fn closed_form_branches_agree_at_the_switch() {
        // Either side of |c| T^2 = 1 both branches are valid; they must agree.
        let t = DEFAULT_DT;
        for &(v0, acc, b, c) in &[
            (10.0, 2.0, 1.5, 0.9 / (t * t)),
            (25.0, -4.0, -3.0, 1.1 / (t * t)),
            (5.0, 1.0, 0.2, -1.0 / (t * t)),
            (40.0, 5.0, 8.0, 2.0 / (t * t)),
        ] {
            let s = quadratic_phase_series(t, v0, acc, b, c);
            let f = quadratic_phase_fresnel(t, v0, acc, b, c);
            assert!(s.sub(f).norm1() < 1e-11, "series {s:?} vs fresnel {f:?} at b = {b}, c = {c}");
        }
    }
}
