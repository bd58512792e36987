//! Helpers shared by the observation models' tests: a batch of rows (poses,
//! contexts, AV poses and each row's items), the check that a model's tape
//! path gives the plain path's row log-densities, and the point model's fixtures.

#![allow(dead_code)] // each test file uses what it needs

use autodiff::nn::ParamStore;
use autodiff::{Tape, Tensor};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::Pose;
use ssm::models::observation::edges::{edge_coords, edge_lengths, to_box_frame};
use ssm::models::observation::{ObsContext, ObservationModel, PointObservationModel, PosesRef, RowVars, Scratch};

/// One batch of rows: poses, contexts (varying extents), AV poses and items.
pub struct Rows<I> {
    /// The object's pose per row.
    pub poses: Vec<Pose>,
    /// The observation context per row.
    pub ctxs: Vec<ObsContext>,
    /// The AV's pose per row.
    pub av: Vec<Pose>,
    /// The observed items (points, detections) per row.
    pub items: Vec<Vec<I>>,
}

impl<I> Rows<I> {
    /// Each row's items as a slice.
    pub fn item_slices(&self) -> Vec<&[I]> {
        self.items.iter().map(|p| p.as_slice()).collect()
    }

    /// `x, y, yaw, length, width` as tensors of shape `[R]`.
    pub fn inputs(&self) -> Vec<Tensor<f64>> {
        let c = |f: &dyn Fn(usize) -> f64| Tensor::from_vec((0..self.poses.len()).map(f).collect());
        vec![
            c(&|i| self.poses[i].x),
            c(&|i| self.poses[i].y),
            c(&|i| self.poses[i].yaw),
            c(&|i| self.ctxs[i].length),
            c(&|i| self.ctxs[i].width),
        ]
    }
}

/// `model.log_likelihood_rows` of `rows` on an f64 and an f32 tape against the
/// plain path row by row: the f64 tape within 1e-10 (relative), the f32 tape
/// within `f32_per_item` per item plus 1e-6 (relative). Returns the f64 values.
pub fn assert_tape_rows_match_plain<M: ObservationModel>(
    model: &M,
    store: &ParamStore<f64>,
    rows: &Rows<M::Item>,
    f32_per_item: f64,
) -> Vec<f64> {
    let items = rows.item_slices();
    let tape = Tape::<f64>::new();
    let params = store.bind(&tape);
    let rv = RowVars::from_poses(&tape, &rows.poses, &rows.ctxs);
    let out = model.log_likelihood_rows(&params, &rv, &rows.av, &items).to_tensor();
    assert_eq!(out.shape(), &[rows.poses.len()]);
    let store32 = store.cast::<f32>();
    let tape32 = Tape::<f32>::new();
    let params32 = store32.bind(&tape32);
    let rv32 = RowVars::from_poses(&tape32, &rows.poses, &rows.ctxs);
    let out32 = model.log_likelihood_rows(&params32, &rv32, &rows.av, &items).to_tensor();
    for (r, row_items) in items.iter().enumerate() {
        let mut plain = [0.0];
        let p = rows.poses[r];
        let (x, y, yaw) = ([p.x], [p.y], [p.yaw]);
        let poses = PosesRef::new(&x, &y, &yaw);
        model.log_likelihood(store, &rows.ctxs[r], poses, row_items, &mut Scratch::new(), &mut plain);
        let v = out.data()[r];
        assert!((v - plain[0]).abs() < 1e-10 * plain[0].abs().max(1.0), "row {r}: tape {v} vs plain {}", plain[0]);
        let v32 = out32.data()[r] as f64;
        assert!((v32 - v).abs() <= f32_per_item * row_items.len() as f64 + 1e-6 * v.abs(), "row {r}: f32 {v32} vs {v}");
    }
    out.data().to_vec()
}

/// A point observation network with parameters drawn from `seed`.
pub fn model(seed: u64) -> (PointObservationModel, ParamStore<f64>) {
    let mut store = ParamStore::new();
    let m = PointObservationModel::init_params(&mut store, "obs", &mut StdRng::seed_from_u64(seed));
    (m, store)
}

/// A car-sized box seen from an AV at `(-15, 8)`.
pub fn ctx() -> ObsContext {
    ObsContext::new(Pose { x: -15.0, y: 8.0, yaw: 0.3 }, 4.4, 1.9)
}

/// Poses scattered around `(0.3, -0.2, 0.4)`.
pub fn poses(n: usize, rng: &mut StdRng) -> Vec<Pose> {
    (0..n)
        .map(|_| Pose {
            x: 0.3 + rng.random_range(-0.5..0.5),
            y: -0.2 + rng.random_range(-0.5..0.5),
            yaw: 0.4 + rng.random_range(-0.3..0.3),
        })
        .collect()
}

/// The poses' `x`, `y` and `yaw` as separate vectors.
pub fn soa(poses: &[Pose]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    (poses.iter().map(|p| p.x).collect(), poses.iter().map(|p| p.y).collect(), poses.iter().map(|p| p.yaw).collect())
}

/// `v` in f32.
pub fn to32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// Whether `p` is at least `margin` from every kink of the density at `pose`: the
/// ends of the edges (where the soft uniform changes formula) and the Laplace modes.
pub fn clear_of_kinks(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    ctx: &ObsContext,
    pose: Pose,
    p: [f64; 2],
    margin: f64,
) -> bool {
    let m = model.edge_mixture(store, ctx, pose);
    let (u, v) = to_box_frame(pose, p);
    let coords = edge_coords(u, v, 0.5 * ctx.length, 0.5 * ctx.width);
    let lens = edge_lengths(ctx.length, ctx.width);
    (0..4).all(|e| {
        let (a, b) = coords[e];
        a.abs() > margin && (a - lens[e]).abs() > margin && (b - m.mu[e]).abs() > margin
    })
}

/// Contexts for `r` rows: AVs along `y = 8` and car-sized extents drawn from `rng`.
pub fn row_contexts(r: usize, rng: &mut StdRng) -> Vec<ObsContext> {
    (0..r)
        .map(|i| {
            ObsContext::new(
                Pose { x: -15.0 + i as f64, y: 8.0, yaw: 0.3 },
                rng.random_range(3.5..5.0),
                rng.random_range(1.6..2.1),
            )
        })
        .collect()
}
