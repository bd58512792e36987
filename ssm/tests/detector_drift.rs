//! The detector drift (`ssm::models::drift`) in the extended model: the filter's
//! f32 path and the estimators' tape path compute the same observation
//! log-densities at drifted states, the tape gradients in the drift's
//! parameters and in the states (offsets included) match finite differences in
//! f64, a drift of vanishing sd is the model without it, and the AOTLL that
//! integrates the drift out converges on its grid.

use autodiff::gradcheck::GradCheck;
use autodiff::{Tape, Tensor, Var};
use rand::SeedableRng;
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{Dataset, ObservationKind};
use ssm::evaluation::metrics::model_aotll;
use ssm::models::drift::{DetectorDrift, DRIFT_DIMS};
use ssm::models::extended::{ExtendedSsm, ExtensibleObservation, Extension};
use ssm::models::params::{AnyPolicy, ModelVisitor, Models};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::{NeuralPolicy, STATE_DIM};
use ssm::models::{Batch, Block, DifferentiableModel, ParticleModel};

/// Drifted state rows: the vehicle's state then three standardised offsets.
const DIM: usize = STATE_DIM + DRIFT_DIMS;

/// A small box dataset (2 scenes of 2 objects, 5 steps) from generator seed `seed`.
fn data(seed: u64) -> Dataset {
    let config = HiddenConfig {
        scenes: 2,
        objects_per_scene: 2,
        steps: 5,
        ..HiddenConfig::quick(ObservationKind::Boxes, HiddenEffect::None, seed)
    };
    generate_hidden(&config).expect("generated")
}

fn models() -> Models {
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    Models::initial(
        ObservationKind::Boxes,
        AnyPolicy::Neural(NeuralPolicy::new(&mut rng).with_initial_sds(0.7, 0.03)),
        3,
    )
}

/// A drift away from its start, persistence and sds differing per offset.
fn drift_raw(scale: f64) -> Vec<f64> {
    let mut v = DetectorDrift::initial().data().to_vec();
    for (k, x) in v.iter_mut().enumerate() {
        *x += scale * (0.2 + 0.1 * k as f64);
    }
    v
}

/// Rows at the true states of every observed step `t >= 1` with offsets `u`
/// drawn from `seed`, the previous step's (offsets too) and the actions.
struct Rows {
    blocks: Vec<Block>,
    now: Vec<[f64; DIM]>,
    prev: Vec<[f64; DIM]>,
    actions: Vec<[f64; 2]>,
}

fn rows(data: &Dataset, model: &impl ParticleModel, seed: u64) -> Rows {
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
    let (states, actions) = (data.states().expect("truth"), data.actions().expect("truth"));
    let mut out = Rows { blocks: Vec::new(), now: Vec::new(), prev: Vec::new(), actions: Vec::new() };
    for o in 0..data.objects().len() {
        for t in 1..data.steps() {
            if model.observation_count(o, t) == 0 {
                continue;
            }
            let mut row = |s: [f64; STATE_DIM]| {
                let mut r = [0.0; DIM];
                r[..STATE_DIM].copy_from_slice(&s);
                r[STATE_DIM..].iter_mut().for_each(|u| *u = StandardNormal.sample(&mut rng));
                r
            };
            out.now.push(row(states.get(o, t).expect("state").to_array()));
            out.prev.push(row(states.get(o, t - 1).expect("state").to_array()));
            let a = actions.get(o, t).expect("action");
            out.actions.push([a.accel, a.pinch]);
            out.blocks.push(Block { object: o, t, len: 1 });
        }
    }
    out
}

fn columns<'t, const D: usize>(tape: &'t Tape<f64>, rows: &[[f64; D]], dims: usize) -> Vec<Var<'t, f64>> {
    (0..dims).map(|k| tape.constant(Tensor::from_vec(rows.iter().map(|r| r[k]).collect()))).collect()
}

struct Check {
    extension: Option<Extension>,
    seed: u64,
}

impl ModelVisitor for Check {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        let ext_raw = self.extension.map_or_else(Vec::new, |e| e.initial().data().iter().map(|v| v + 0.2).collect());
        let drift = drift_raw(1.0);
        let model = ExtendedSsm::new(base, self.extension, &ext_raw)
            .and_then(|m| m.with_drift(Some(&drift)))
            .expect("a drift applies to boxes");
        assert_eq!(model.state_dim(), DIM);
        let r = rows(model.data(), &model, self.seed);
        assert!(!r.blocks.is_empty());

        // The filter's f32 path and the tape's f64 path agree, row by row.
        let tape = Tape::<f64>::no_record();
        let params = model.bind(&tape);
        let tape_values =
            model.observation_log_density(&params, &r.blocks, &columns(&tape, &r.now, DIM)).value().clone();
        let mut scratch = model.new_scratch();
        for (i, b) in r.blocks.iter().enumerate() {
            let x: Vec<f32> = r.now[i].iter().map(|&v| v as f32).collect();
            let mut out = [0.0f32];
            assert!(model.observation_loglik(Batch { object: b.object, t: b.t, n: 1 }, &x, &mut out, &mut scratch));
            let want = tape_values.data()[i];
            assert!(
                (out[0] as f64 - want).abs() < 2e-3 * want.abs().max(1.0),
                "row {i}: f32 {} vs tape {want}",
                out[0]
            );
        }

        // Gradients: the observation term in the drift's parameter and every state
        // component (offsets included), the transition term in every parameter.
        let theta = model.parameters();
        let drift_index = theta.len() - 1;
        let check = GradCheck { step: 1e-5, rel_tol: 1e-5, ..GradCheck::default() };
        let report = check
            .check(
                |tape, vars| {
                    let mut params: Vec<Var<'_, f64>> = theta.iter().map(|p| tape.constant(p.clone())).collect();
                    params[drift_index] = vars[0];
                    model.observation_log_density(&params, &r.blocks, &vars[1..]).sum()
                },
                &std::iter::once(theta[drift_index].clone())
                    .chain((0..DIM).map(|k| Tensor::from_vec(r.now.iter().map(|row| row[k]).collect())))
                    .collect::<Vec<_>>(),
            )
            .unwrap_or_else(|e| panic!("{:?}, observation: {e}", self.extension));
        assert!(report.comparisons > 10);
        let report = check
            .check(
                |tape, vars| {
                    let (prev, next) = (columns(tape, &r.prev, DIM), columns(tape, &r.now, DIM));
                    let a = columns(tape, &r.actions, 2);
                    model.transition_log_density(vars, &r.blocks, &prev, &next, &a).sum()
                },
                &theta,
            )
            .unwrap_or_else(|e| panic!("{:?}, transition: {e}", self.extension));
        assert!(report.comparisons > 10);
    }
}

#[test]
fn plain_and_tape_paths_agree_and_gradients_match_finite_differences() {
    for (extension, seed) in [(None, 1), (Some(Extension::HeadingFlip), 2)] {
        models().visit(&data(seed), Check { extension, seed }).expect("model");
    }
}

struct Vanishing;

impl ModelVisitor for Vanishing {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        let plain = ExtendedSsm::new(base, None, &[]).expect("base");
        // sds of e^-24: the offsets move nothing a float can see.
        let mut raw = drift_raw(1.0);
        raw[DRIFT_DIMS..].iter_mut().for_each(|v| *v = -12.0);
        let drifting = ExtendedSsm::new(base, None, &[]).and_then(|m| m.with_drift(Some(&raw))).expect("drift");
        let r = rows(base.data(), &drifting, 4);
        let tape = Tape::<f64>::no_record();
        let with = drifting.observation_log_density(&drifting.bind(&tape), &r.blocks, &columns(&tape, &r.now, DIM));
        let without = plain.observation_log_density(&plain.bind(&tape), &r.blocks, &columns(&tape, &r.now, STATE_DIM));
        for (x, y) in with.value().data().iter().zip(without.value().data()) {
            assert!((x - y).abs() < 1e-9 * y.abs().max(1.0), "{x} vs {y}");
        }
        // AOTLL integrates the drift out: here it is the plain model's.
        let (a, b) = (model_aotll(base.data(), &drifting, 4).mean, model_aotll(base.data(), &plain, 4).mean);
        let (a, b) = (a.expect("labelled"), b.expect("labelled"));
        assert!((a - b).abs() < 1e-4, "{a} vs {b}");
    }
}

#[test]
fn a_drift_of_vanishing_sd_is_the_model_without_it() {
    models().visit(&data(5), Vanishing).expect("model");
}

struct Grid;

impl ModelVisitor for Grid {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        for scale in [0.5, 2.0] {
            let raw = drift_raw(scale);
            let m = ExtendedSsm::new(base, None, &[]).and_then(|m| m.with_drift(Some(&raw))).expect("drift");
            let aotll = |nodes| model_aotll(base.data(), &m, nodes).mean.expect("labelled");
            // Richardson over 12 and 24 nodes against 24 and 48.
            let (coarse, fine) = (
                aotll(ssm::evaluation::metrics::DRIFT_AOTLL_NODES),
                aotll(2 * ssm::evaluation::metrics::DRIFT_AOTLL_NODES),
            );
            eprintln!("drift sds scale {scale}: AOTLL {coarse} on the default grids, {fine} on grids twice as fine");
            assert!((coarse - fine).abs() < 0.005, "sd scale {scale}: {coarse} vs {fine}");
            // The drift is integrated out, not ignored: the larger one moves the
            // AOTLL (against this unfitted network's wide scales the smaller one
            // barely does).
            let plain = ExtendedSsm::new(base, None, &[]).expect("base");
            let without = model_aotll(base.data(), &plain, 1).mean.expect("labelled");
            assert!(
                scale < 1.0 || (fine - without).abs() > 0.02,
                "sd scale {scale}: {fine} with drift, {without} without"
            );
        }
    }
}

#[test]
fn the_integrated_aotll_converges_on_its_grid() {
    models().visit(&data(6), Grid).expect("model");
}
