//! Helpers shared by the observation models' tests: a batch of rows (poses,
//! contexts, AV poses and each row's items), the check that a model's tape
//! path gives the plain path's row log-densities, finiteness checks, and the
//! point model's fixtures; the score studies' bias criterion; and a dataset
//! rewritten through its CSV files.

use autodiff::gradcheck::GradCheck;
use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::{Dataset, Pose};
use ssm::estimators::study::ScoreStudyRow;
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

/// Checks `model`'s tape row log-likelihoods of `rows` against finite differences
/// (at the default settings), contracted with `weights` (one per row): with
/// respect to every network parameter (rows constant), with at least 100
/// comparisons, and with respect to the rows' states and extents (parameters
/// constant), each compared.
#[track_caller]
pub fn check_row_gradients<M: ObservationModel>(
    model: &M,
    store: &ParamStore<f64>,
    rows: &Rows<M::Item>,
    weights: &[f64],
) {
    let items = rows.item_slices();
    let weights = Tensor::from_vec(weights.to_vec());
    let report = GradCheck::default()
        .check_params(store, |tape, params| {
            let rv = RowVars::from_poses(tape, &rows.poses, &rows.ctxs);
            (model.log_likelihood_rows(params, &rv, &rows.av, &items) * tape.constant(weights.clone())).sum()
        })
        .unwrap();
    assert!(report.comparisons >= 100, "{report:?}");
    let report = GradCheck::default()
        .check(
            |tape, v| {
                let params = store.bind(tape);
                let rv = RowVars { x: v[0], y: v[1], yaw: v[2], length: v[3], width: v[4] };
                (model.log_likelihood_rows(&params, &rv, &rows.av, &items) * tape.constant(weights.clone())).sum()
            },
            &rows.inputs(),
        )
        .unwrap();
    assert_eq!(report.comparisons, 5 * rows.poses.len());
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

/// Rows of `per_row` points each at poses and contexts drawn from `seed`: every
/// point is a candidate `draw(ctx, pose, rng)` kept if [`clear_of_kinks`] by 3 cm.
pub fn kink_free_rows(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    r: usize,
    per_row: usize,
    seed: u64,
    mut draw: impl FnMut(&ObsContext, Pose, &mut StdRng) -> [f64; 2],
) -> Rows<[f64; 2]> {
    let mut rng = StdRng::seed_from_u64(seed);
    let ps = poses(r, &mut rng);
    let ctxs = row_contexts(r, &mut rng);
    let points = (0..r)
        .map(|i| {
            let mut pts = Vec::new();
            while pts.len() < per_row {
                let cand = draw(&ctxs[i], ps[i], &mut rng);
                if clear_of_kinks(model, store, &ctxs[i], ps[i], cand, 0.03) {
                    pts.push(cand);
                }
            }
            pts
        })
        .collect();
    let av = ctxs.iter().map(|c| c.av).collect();
    Rows { poses: ps, ctxs, av, items: points }
}

/// Asserts that the plain path's log-likelihoods `out` of `items` at `poses` (one
/// per pose) in context `ctx` and its per-item log-densities equal `reference(pose,
/// item)` (summed over the items for `out`) within `tol` relative (floor 1).
#[track_caller]
// A test helper: the model, its inputs, the outputs under test, the tolerance and the reference are all needed.
#[allow(clippy::too_many_arguments)]
pub fn assert_plain_matches_reference<M: ObservationModel>(
    model: &M,
    store: &ParamStore<f64>,
    ctx: &ObsContext,
    poses: &[Pose],
    items: &[M::Item],
    out: &[f64],
    tol: f64,
    reference: impl Fn(Pose, &M::Item) -> f64,
) {
    let mut per_item = vec![0.0; items.len()];
    for (i, p) in poses.iter().enumerate() {
        let want: Vec<f64> = items.iter().map(|q| reference(*p, q)).collect();
        let total: f64 = want.iter().sum();
        assert!((out[i] - total).abs() < tol * total.abs().max(1.0), "pose {i}: {} vs {total}", out[i]);
        model.log_density_items(store, ctx, *p, items, &mut per_item);
        for (a, b) in per_item.iter().zip(&want) {
            assert!((a - b).abs() < tol * b.abs().max(1.0), "pose {i}: item {a} vs {b}");
        }
    }
}

/// Asserts that `model`'s log-likelihoods of `items` at the poses `xs`, `ys`,
/// `yaws` (one row each) in context `ctx` are finite on the plain path in f64 and
/// in f32, and on an f32 tape with tracked rows, together with their gradients.
#[track_caller]
pub fn assert_finite_at<M: ObservationModel>(
    model: &M,
    store: &ParamStore<f64>,
    ctx: &ObsContext,
    (xs, ys, yaws): (&[f64], &[f64], &[f64]),
    items: &[M::Item],
) {
    let n = xs.len();
    let mut out = vec![0.0; n];
    model.log_likelihood(store, ctx, PosesRef::new(xs, ys, yaws), items, &mut Scratch::new(), &mut out);
    assert!(out.iter().all(|v| v.is_finite()), "f64 {out:?}");
    let s32 = store.cast::<f32>();
    let (x32, y32, yaw32) = (to32(xs), to32(ys), to32(yaws));
    let mut out32 = vec![0.0f32; n];
    model.log_likelihood(&s32, ctx, PosesRef::new(&x32, &y32, &yaw32), items, &mut Scratch::new(), &mut out32);
    assert!(out32.iter().all(|v| v.is_finite()), "f32 {out32:?}");
    // Tape values and gradients (f32, the estimators' type).
    let tape = Tape::<f32>::new();
    let params = s32.bind(&tape);
    let rv = f32_row_params(&tape, &x32, &y32, &yaw32, ctx.length as f32, ctx.width as f32);
    let rows: Vec<&[M::Item]> = vec![items; n];
    let v = model.log_likelihood_rows(&params, &rv, &vec![ctx.av; n], &rows);
    assert_finite_with_gradients("tape", &tape, &params, v, &[rv.x, rv.y, rv.yaw, rv.length, rv.width]);
}

/// Rows on an f32 tape, all tracked: positions and headings `xs`, `ys`, `yaws`,
/// and every row `length` by `width`.
pub fn f32_row_params<'t>(
    tape: &'t Tape<f32>,
    xs: &[f32],
    ys: &[f32],
    yaws: &[f32],
    length: f32,
    width: f32,
) -> RowVars<'t, f32> {
    RowVars {
        x: tape.param(Tensor::from_vec(xs.to_vec())),
        y: tape.param(Tensor::from_vec(ys.to_vec())),
        yaw: tape.param(Tensor::from_vec(yaws.to_vec())),
        length: tape.param(Tensor::full(&[xs.len()], length)),
        width: tape.param(Tensor::full(&[xs.len()], width)),
    }
}

/// Asserts that the row values `out` on `tape` are finite, and so are the gradients
/// of their sum for every parameter in `params` and every var in `inputs`; `what`
/// names the case in the messages.
#[track_caller]
pub fn assert_finite_with_gradients<'t>(
    what: &str,
    tape: &'t Tape<f32>,
    params: &BoundParams<'t, f32>,
    out: Var<'t, f32>,
    inputs: &[Var<'t, f32>],
) {
    assert!(out.to_tensor().all_finite(), "{what}: {:?}", out.to_tensor());
    let grads = tape.backward(out.sum());
    assert!(params.gradients(&grads).iter().all(|g| g.all_finite()), "{what}: parameter gradients");
    for (k, v) in inputs.iter().enumerate() {
        assert!(grads.wrt(*v).all_finite(), "{what}: gradient of input {k}");
    }
}

/// Asserts that a score study's row is unbiased: `|bias| <= se_multiple * se +
/// 0.05 * sd` (a bias within `se_multiple` standard errors, plus 5% of one run's
/// spread); `what` names the case in the message.
#[track_caller]
pub fn assert_unbiased(what: &str, r: &ScoreStudyRow, se_multiple: f64) {
    assert!(
        r.bias.abs() <= se_multiple * r.se + 0.05 * r.sd,
        "{what} {}: bias {} se {} sd {} (exact {})",
        r.component,
        r.bias,
        r.se,
        r.sd,
        r.exact
    );
}

/// `data` with the rows of one of its CSV files (`file`, e.g. `boxes.csv`)
/// rewritten by `edit` and read back (through a temporary directory named by
/// `tag`). `edit` gets the column index of a header name and one row's fields.
pub fn with_csv_rows_rewritten(
    data: &Dataset,
    file: &str,
    tag: &str,
    mut edit: impl FnMut(&dyn Fn(&str) -> usize, &mut Vec<String>),
) -> Dataset {
    let dir = std::env::temp_dir().join(format!("ssm-{tag}-{}", std::process::id()));
    data.write(&dir).unwrap();
    let path = dir.join(file);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("{file}: no `{name}`"));
    let mut out = header.join(",") + "\n";
    for line in lines {
        let mut fields: Vec<String> = line.split(',').map(str::to_string).collect();
        edit(&col, &mut fields);
        out += &(fields.join(",") + "\n");
    }
    std::fs::write(&path, out).unwrap();
    let rewritten = Dataset::read(&dir).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    rewritten
}
