//! Point observation model (SPEC §3): the soft uniform against its definition, the
//! fast kernels against an independent f64 reference, f32 against f64, the fused
//! tape path against the plain path and against the same density composed from
//! engine ops, gradients against finite differences (parameters, states, extents),
//! finiteness at extreme inputs, normalisation, and the sampler against the density.

use crate::common::{
    assert_finite_at, assert_plain_matches_reference, assert_tape_rows_match_plain, check_row_gradients, ctx,
    kink_free_rows, model, poses, soa, to32, Rows,
};
use autodiff::nn::{BoundParams, ParamStore};
use autodiff::{Parallelism, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use ssm::data::Pose;
use ssm::models::observation::edges::{
    edge_coords, edge_lengths, from_box_frame, log_soft_uniform, sample_soft_uniform, to_box_frame,
};
use ssm::models::observation::{
    av_features_on_tape, ObsContext, ObservationModel, PointObservationModel, PosesRef, RowVars, Scratch,
};

const SOFT: f64 = 0.05;

fn lse(v: &[f64]) -> f64 {
    let m = v.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b));
    m + v.iter().map(|x| (x - m).exp()).sum::<f64>().ln()
}

/// Independent f64 reference of `log g(p | pose)`: the network's mixture, then SPEC
/// §3's formula term by term with the branchy soft uniform.
fn reference(model: &PointObservationModel, store: &ParamStore<f64>, ctx: &ObsContext, pose: Pose, p: [f64; 2]) -> f64 {
    let m = model.edge_mixture(store, ctx, pose);
    let (u, v) = to_box_frame(pose, p);
    let coords = edge_coords(u, v, 0.5 * ctx.length, 0.5 * ctx.width);
    let lens = edge_lengths(ctx.length, ctx.width);
    let terms: Vec<f64> = (0..4)
        .map(|e| {
            m.phi[e].ln() + log_soft_uniform(coords[e].0, lens[e], SOFT)
                - (coords[e].1 - m.mu[e]).abs() / m.b[e]
                - (2.0 * m.b[e]).ln()
        })
        .collect();
    lse(&terms)
}

/// Points from the model at `pose` plus a few anywhere within 3 m.
fn points(
    model: &PointObservationModel,
    store: &ParamStore<f64>,
    pose: Pose,
    n: usize,
    rng: &mut StdRng,
) -> Vec<[f64; 2]> {
    let mut pts = Vec::new();
    model.sample(store, &ctx(), pose, n, rng, &mut pts);
    for _ in 0..3 {
        pts.push([pose.x + rng.random_range(-3.0..3.0), pose.y + rng.random_range(-3.0..3.0)]);
    }
    pts
}

#[test]
fn soft_uniform_is_the_convolution_and_is_normalised() {
    for &len in &[0.3, 1.9, 4.4] {
        // Normalisation by the trapezoid rule over [-3, len + 3] (tails e^{-60}).
        let h = 1e-4;
        let n = ((len + 6.0) / h) as usize;
        let total: f64 = (0..=n)
            .map(|k| {
                let w = if k == 0 || k == n { 0.5 } else { 1.0 };
                w * log_soft_uniform(-3.0 + k as f64 * h, len, SOFT).exp()
            })
            .sum::<f64>()
            * h;
        assert!((total - 1.0).abs() < 1e-6, "len {len}: integral {total}");
        // Against the convolution integral (1/len) int_0^len Laplace(a - t; 0, s) dt by quadrature.
        for &a in &[-0.2, -0.01, 0.0, 0.03, len / 2.0, len - 0.02, len, len + 0.1] {
            let m = 200_000;
            let conv: f64 = (0..m)
                .map(|k| {
                    let t = (k as f64 + 0.5) * len / m as f64;
                    (-(a - t).abs() / SOFT).exp() / (2.0 * SOFT)
                })
                .sum::<f64>()
                / m as f64;
            let got = log_soft_uniform(a, len, SOFT).exp();
            assert!((got - conv).abs() < 1e-6 * conv.max(1.0), "len {len}, a {a}: {got} vs {conv}");
        }
        // The pieces meet with equal values and slopes at both ends.
        for &end in &[0.0, len] {
            let d = 1e-7;
            let (lo, hi) = (log_soft_uniform(end - d, len, SOFT), log_soft_uniform(end + d, len, SOFT));
            assert!((lo - hi).abs() < 2e-5, "jump at {end}");
            let slope = |x: f64| (log_soft_uniform(x + 1e-6, len, SOFT) - log_soft_uniform(x - 1e-6, len, SOFT)) / 2e-6;
            assert!((slope(end - 1e-5) - slope(end + 1e-5)).abs() < 1e-2, "slope jump at {end}");
        }
    }
    // Finite far away and for tiny edges.
    for &a in &[-1e4, 1e4, -1e30, 1e30] {
        assert!(log_soft_uniform(a, 4.4, SOFT).is_finite());
    }
    assert!(log_soft_uniform(0.0005, 1e-3, SOFT).is_finite() && log_soft_uniform(-1e4, 1e-9, SOFT).is_finite());
    // A soft-uniform draw is uniform plus Laplace: mean len/2, variance len^2/12 + 2 s^2.
    let mut rng = StdRng::seed_from_u64(9);
    let n = 200_000;
    let xs: Vec<f64> = (0..n).map(|_| sample_soft_uniform(2.0, SOFT, &mut rng)).collect();
    let mean = xs.iter().sum::<f64>() / n as f64;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
    let sd_mean = (4.0 / 12.0 + 2.0 * SOFT * SOFT).sqrt() / (n as f64).sqrt();
    assert!((mean - 1.0).abs() < 5.0 * sd_mean, "mean {mean}");
    assert!((var - (4.0 / 12.0 + 2.0 * SOFT * SOFT)).abs() < 5e-3, "variance {var}");
}

#[test]
fn plain_kernel_matches_reference_in_f64_and_f32() {
    let (model, store) = model(1);
    let mut rng = StdRng::seed_from_u64(2);
    let ps = poses(37, &mut rng);
    let pts = points(&model, &store, ps[0], 20, &mut rng);
    let (xs, ys, yaws) = soa(&ps);
    let ctx = ctx();
    let mut out = vec![0.0; ps.len()];
    let mut scratch = Scratch::new();
    model.log_likelihood(&store, &ctx, PosesRef::new(&xs, &ys, &yaws), &pts, &mut scratch, &mut out);
    assert_plain_matches_reference(&model, &store, &ctx, &ps, &pts, &out, 1e-10, |p, &q| {
        reference(&model, &store, &ctx, p, q)
    });
    // f32 (fast exp/ln/tanh, f32 coordinates). Per point the error is at most about
    // |d log g / d position| (<= 1/b + 1/s <= 120 per m) times the coordinate rounding
    // (~2e-6 m near 20 m), ~3e-4, plus ~1e-6 relative from the fast transcendentals.
    let store32 = store.cast::<f32>();
    let (x32, y32, w32) = (to32(&xs), to32(&ys), to32(&yaws));
    let mut out32 = vec![0.0f32; ps.len()];
    let mut scratch32 = Scratch::new();
    model.log_likelihood(&store32, &ctx, PosesRef::new(&x32, &y32, &w32), &pts, &mut scratch32, &mut out32);
    for i in 0..ps.len() {
        let tol = 3e-4 * pts.len() as f64 + 1e-6 * out[i].abs();
        assert!((out32[i] as f64 - out[i]).abs() < tol, "particle {i}: f32 {} vs f64 {}", out32[i], out[i]);
    }
    // Reusing the scratch for another batch size gives the same numbers.
    let mut again = vec![0.0; 5];
    model.log_likelihood(&store, &ctx, PosesRef::new(&xs[..5], &ys[..5], &yaws[..5]), &pts, &mut scratch, &mut again);
    assert_eq!(&again[..], &out[..5]);
}

/// Rows whose points are model draws, one in five replaced by a point anywhere
/// within 3 m, all clear of the density's kinks.
fn rows(model: &PointObservationModel, store: &ParamStore<f64>, r: usize, per_row: usize, seed: u64) -> Rows<[f64; 2]> {
    kink_free_rows(model, store, r, per_row, seed, |ctx, pose, rng| {
        let mut cand = Vec::new();
        model.sample(store, ctx, pose, 1, rng, &mut cand);
        if rng.random::<f64>() < 0.2 {
            cand[0] = [pose.x + rng.random_range(-3.0..3.0), pose.y + rng.random_range(-3.0..3.0)];
        }
        cand[0]
    })
}

#[test]
fn tape_rows_match_plain_path() {
    let (model, store) = model(3);
    let mut b = rows(&model, &store, 6, 9, 4);
    b.items[2].clear(); // a row without observation contributes 0
                        // f32 tape: the same error budget as the plain f32 path.
    let out = assert_tape_rows_match_plain(&model, &store, &b, 3e-4);
    assert_eq!(out[2], 0.0);
}

/// The same density composed from engine ops (soft uniform by `select` over its
/// three pieces, mixture by `logsumexp`, rows by `scatter_add`): an independent
/// check of the fused kernel's partial derivatives.
fn composed_rows<'t>(
    model: &PointObservationModel,
    params: &BoundParams<'t, f64>,
    rows: &RowVars<'t, f64>,
    av: &[Pose],
    items: &[&[[f64; 2]]],
) -> Var<'t, f64> {
    let tape = rows.x.tape();
    let r = rows.len();
    let o = model.mlp().forward(params, av_features_on_tape(rows, av));
    let logphi = o.slice(1, 0, 4).log_softmax(1);
    let mu = o.slice(1, 4, 4).mul_scalar(0.2);
    let b = o.slice(1, 8, 4).softplus().mul_scalar(0.2).add_scalar(0.01);
    let idx: Vec<usize> = items.iter().enumerate().flat_map(|(i, p)| p.iter().map(move |_| i)).collect();
    let pts: Vec<[f64; 2]> = items.iter().flat_map(|p| p.iter().copied()).collect();
    let q = idx.len();
    let c = |v: Vec<f64>| tape.constant(Tensor::from_vec(v));
    let px = c(pts.iter().map(|p| p[0]).collect());
    let py = c(pts.iter().map(|p| p[1]).collect());
    let g = |v: Var<'t, f64>| v.gather(0, &idx);
    let (x, y, yaw, l, w) = (g(rows.x), g(rows.y), g(rows.yaw), g(rows.length), g(rows.width));
    let (dx, dy) = (px - x, py - y);
    let (cs, sn) = (yaw.cos(), yaw.sin());
    let u = cs * dx + sn * dy;
    let v = cs * dy - sn * dx;
    let (hl, hw) = (l.mul_scalar(0.5), w.mul_scalar(0.5));
    let alphas = [v + hw, hl - u, hw - v, u + hl];
    let betas = [u - hl, v - hw, -u - hl, -v - hw];
    let lens = [w, l, w, l];
    let mut terms = Vec::new();
    for e in 0..4 {
        let (a, len) = (alphas[e], lens[e]);
        let d2 = len - a;
        let (av_, lv) = (a.to_tensor(), len.to_tensor());
        let below: Vec<bool> = av_.data().iter().map(|&x| x < 0.0).collect();
        let above: Vec<bool> = av_.data().iter().zip(lv.data()).map(|(&x, &l)| x > l).collect();
        let tail = (len.mul_scalar(-1.0 / SOFT).exp().neg().add_scalar(1.0)).ln() - std::f64::consts::LN_2 - len.ln();
        let inside = ((a.relu().mul_scalar(-1.0 / SOFT).exp() + d2.relu().mul_scalar(-1.0 / SOFT).exp())
            .mul_scalar(-0.5)
            .add_scalar(1.0))
        .ln()
            - len.ln();
        let soft = tape.select(
            &below,
            a.mul_scalar(1.0 / SOFT) + tail,
            tape.select(&above, d2.mul_scalar(1.0 / SOFT) + tail, inside),
        );
        let col = |m: Var<'t, f64>| m.slice(1, e, 1).reshape(&[r]).gather(0, &idx);
        let (lp, mu_e, b_e) = (col(logphi), col(mu), col(b));
        let lap = -((betas[e] - mu_e).abs() / b_e) - b_e.mul_scalar(2.0).ln();
        terms.push((lp + soft + lap).reshape(&[q, 1]));
    }
    tape.concat(&terms, 1).logsumexp(1, false).scatter_add(0, &idx, r)
}

#[test]
fn fused_tape_matches_composed_tape() {
    let (model, store) = model(5);
    let b = rows(&model, &store, 4, 7, 6);
    let items = b.item_slices();
    let inputs = b.inputs();
    let weights = Tensor::from_vec(vec![0.7, -1.3, 0.4, 2.0]);
    let eval = |composed: bool| {
        let tape = Tape::<f64>::new();
        let params = store.bind(&tape);
        let v: Vec<Var<'_, f64>> = inputs.iter().map(|t| tape.param(t.clone())).collect();
        let rv = RowVars { x: v[0], y: v[1], yaw: v[2], length: v[3], width: v[4] };
        let out = if composed {
            composed_rows(&model, &params, &rv, &b.av, &items)
        } else {
            model.log_likelihood_rows(&params, &rv, &b.av, &items)
        };
        let loss = (out * tape.constant(weights.clone())).sum();
        let grads = tape.backward(loss);
        let mut all = params.gradients(&grads);
        all.extend(v.iter().map(|&x| grads.wrt(x)));
        (out.to_tensor(), all)
    };
    let (vf, gf) = eval(false);
    let (vc, gc) = eval(true);
    for (a, b) in vf.data().iter().zip(vc.data()) {
        assert!((a - b).abs() < 1e-10 * b.abs().max(1.0), "value {a} vs {b}");
    }
    for (k, (a, b)) in gf.iter().zip(&gc).enumerate() {
        for (x, y) in a.data().iter().zip(b.data()) {
            assert!((x - y).abs() < 1e-9 * y.abs().max(1.0), "gradient tensor {k}: fused {x} vs composed {y}");
        }
    }
}

#[test]
fn tape_gradients_match_finite_differences() {
    let (model, store) = model(7);
    let b = rows(&model, &store, 3, 6, 8);
    // With respect to every network parameter (rows constant), then to the states
    // and extents (parameters constant).
    check_row_gradients(&model, &store, &b, &[1.0, -0.6, 0.3]);
}

#[test]
fn parallel_rows_do_not_change_results() {
    let (model, store) = model(11);
    // 600 rows x 30 points: above the fused kernel's parallel threshold (16384 pairs).
    let mut rng = StdRng::seed_from_u64(12);
    let ps = poses(600, &mut rng);
    let c = ctx();
    let ctxs = vec![c; 600];
    let av = vec![c.av; 600];
    let pts = points(&model, &store, ps[0], 27, &mut rng);
    let items: Vec<&[[f64; 2]]> = vec![&pts[..]; 600];
    let run = |par: Parallelism| {
        let tape = Tape::<f32>::new().with_parallelism(par);
        let s32 = store.cast::<f32>();
        let params = s32.bind(&tape);
        let rv = RowVars::from_poses(&tape, &ps, &ctxs);
        let out = model.log_likelihood_rows(&params, &rv, &av, &items);
        let g = params.gradients(&tape.backward(out.sum()));
        (out.to_tensor(), g)
    };
    assert_eq!(run(Parallelism::Serial), run(Parallelism::Rayon));
}

#[test]
fn extreme_inputs_stay_finite() {
    let (model, store) = model(13);
    let c = ctx();
    let pose = Pose { x: 0.3, y: -0.2, yaw: 0.4 };
    // Points far along an edge's line (alpha = +-1e4 m, beta ~ 0), far out (beta = 1e4 m), both.
    let mut pts = Vec::new();
    for &(u, v) in
        &[(1e4, 0.95), (-1e4, 0.95), (2.2, 1e4), (2.2, -1e4), (1e4, 1e4), (-1e4, -3e3), (0.0, 0.0), (2.2, 0.95)]
    {
        pts.push(from_box_frame(pose, u, v));
    }
    let mut per = vec![0.0; pts.len()];
    model.log_density_items(&store, &c, pose, &pts, &mut per);
    assert!(per.iter().all(|v| v.is_finite()), "{per:?}");
    // 1e4 m out, the log-density falls linearly with the distance: about -1e4 / b or -1e4 / s.
    assert!(per[0] < -1e4 && per[0] > -1e4 / SOFT - 1e3, "{per:?}");
    for (poses_at, size) in [((0.3, -0.2), (4.4, 1.9)), ((1e4, -1e4), (4.4, 1.9)), ((0.3, -0.2), (1e-3, 1e-3))] {
        let cx = ObsContext { length: size.0, width: size.1, ..c };
        let xs = [poses_at.0, poses_at.0 + 1.0, poses_at.0 - 2e4];
        let ys = [poses_at.1, poses_at.1, 1e4];
        let yaws = [0.4, -1e3, 7.0];
        assert_finite_at(&model, &store, &cx, (&xs, &ys, &yaws), &pts);
    }
}

#[test]
fn empty_observations_contribute_zero() {
    let (model, store) = model(14);
    let c = ctx();
    let mut out = [1.0, 2.0];
    model.log_likelihood(
        &store,
        &c,
        PosesRef::new(&[0.0, 1.0], &[0.0, 0.0], &[0.0, 0.0]),
        &[],
        &mut Scratch::new(),
        &mut out,
    );
    assert_eq!(out, [0.0, 0.0]);
    let tape = Tape::<f64>::new();
    let params = store.bind(&tape);
    let rv = RowVars::from_poses(&tape, &[Pose::default(); 2], &[c; 2]);
    let v = model.log_likelihood_rows(&params, &rv, &[c.av; 2], &[&[], &[]]);
    assert_eq!(v.to_tensor().data(), &[0.0, 0.0]);
    assert!(params.gradients(&tape.backward(v.sum())).iter().all(|g| g.data().iter().all(|&x| x == 0.0)));
}

#[test]
fn density_is_normalised_and_the_sampler_agrees_with_it() {
    let (model, store) = model(15);
    let c = ctx();
    let pose = Pose { x: 2.0, y: 1.0, yaw: 0.3 };
    let mix = model.edge_mixture(&store, &c, pose);
    // The quadrature below resolves features down to ~5 cm; this network's scales are wider.
    assert!(mix.b.iter().all(|&b| b > 0.05), "{mix:?}");
    let margin = 4.0 + mix.mu.iter().fold(0.0f64, |a, m| a.max(m.abs()));
    let (hl, hw) = (0.5 * c.length, 0.5 * c.width);
    // Midpoint rule on an h = 1 cm grid in the box frame (the density is rigid-motion
    // invariant), accumulated into 0.25 m cells.
    let (cell, sub) = (0.25, 25);
    let h = cell / sub as f64;
    let (u0, v0) = (-hl - margin, -hw - margin);
    let (nu, nv) = (((2.0 * (hl + margin)) / cell).ceil() as usize, ((2.0 * (hw + margin)) / cell).ceil() as usize);
    let mut prob = vec![0.0; nu * nv];
    let mut row_pts = Vec::with_capacity(nu * sub);
    let mut row_lg = vec![0.0; nu * sub];
    for j in 0..nv * sub {
        let v = v0 + (j as f64 + 0.5) * h;
        row_pts.clear();
        row_pts.extend((0..nu * sub).map(|i| from_box_frame(pose, u0 + (i as f64 + 0.5) * h, v)));
        model.log_density_items(&store, &c, pose, &row_pts, &mut row_lg);
        for (i, lg) in row_lg.iter().enumerate() {
            prob[(j / sub) * nu + i / sub] += lg.exp() * h * h;
        }
    }
    let total: f64 = prob.iter().sum();
    // Missing mass: Laplace tails beyond the margin (< 1e-4 for b <= 0.5 m) plus the
    // midpoint rule's O(h^2 / b^2) error at the Laplace kinks.
    assert!((total - 1.0).abs() < 2e-3, "integral of g over the plane: {total}");
    // Pearson chi-square of samples in the cells, cells with < 5 expected merged.
    let n = 100_000;
    let mut rng = StdRng::seed_from_u64(16);
    let mut pts = Vec::new();
    model.sample(&store, &c, pose, n, &mut rng, &mut pts);
    let mut counts = vec![0usize; nu * nv + 1];
    for p in &pts {
        let (u, v) = to_box_frame(pose, *p);
        let (i, j) = (((u - u0) / cell).floor(), ((v - v0) / cell).floor());
        let k = if i >= 0.0 && j >= 0.0 && (i as usize) < nu && (j as usize) < nv {
            j as usize * nu + i as usize
        } else {
            nu * nv
        };
        counts[k] += 1;
    }
    let (mut chi2, mut bins, mut rest_e, mut rest_o) =
        (0.0, 0usize, n as f64 * (1.0 - total).max(0.0), counts[nu * nv] as f64);
    for k in 0..nu * nv {
        let e = n as f64 * prob[k];
        if e < 5.0 {
            rest_e += e;
            rest_o += counts[k] as f64;
        } else {
            chi2 += (counts[k] as f64 - e).powi(2) / e;
            bins += 1;
        }
    }
    if rest_e > 0.0 {
        chi2 += (rest_o - rest_e).powi(2) / rest_e.max(5.0);
        bins += 1;
    }
    let dof = (bins - 1) as f64;
    // 5 standard deviations of a chi-square with `dof` degrees of freedom.
    assert!(chi2 < dof + 5.0 * (2.0 * dof).sqrt(), "chi-square {chi2:.1} with {dof} degrees of freedom");
}
