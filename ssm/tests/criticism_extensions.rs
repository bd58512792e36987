//! The catalogue's model extensions (`ssm::models::extended`): the filter's
//! f32 path and the estimators' tape path compute the same log-densities, their
//! tape gradients match finite differences in f64, no extension changes the base
//! model before it is switched on, and the replicate sampler agrees with the
//! densities.

use autodiff::gradcheck::GradCheck;
use autodiff::{Tape, Tensor, Var};
use rand::rngs::SmallRng;
use rand::SeedableRng;
use ssm::criticism::checks::geary_ratio;
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::{Action, Dataset, ObservationKind, State};
use ssm::filter::{run_filter, FilterConfig, Sampling};
use ssm::models::extended::{
    mixture_excess_kurtosis, DefensiveProposal, ExtendedSsm, ExtensibleObservation, Extension, RefitScope,
    GAUSSIAN_GEARY_RATIO,
};
use ssm::models::params::{AnyPolicy, ModelVisitor, Models};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::NeuralPolicy;
use ssm::models::{Batch, Drawn, ParticleModel};
use ssm::models::{Block, DifferentiableModel};

/// A small dataset of `kind` (2 scenes of 2 objects, 5 steps).
fn data(kind: ObservationKind) -> Dataset {
    let config =
        HiddenConfig { scenes: 2, objects_per_scene: 2, steps: 5, ..HiddenConfig::quick(kind, HiddenEffect::None, 1) };
    generate_hidden(&config).expect("generated")
}

fn models(kind: ObservationKind) -> Models {
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    Models::initial(kind, AnyPolicy::Neural(NeuralPolicy::new(&mut rng).with_initial_sds(0.7, 0.03)), 3)
}

/// Stored values away from the initial ones, so every term is exercised.
fn raw(ext: Extension) -> Vec<f64> {
    let mut v = ext.initial().data().to_vec();
    for (k, x) in v.iter_mut().enumerate() {
        *x += 0.15 + 0.05 * k as f64;
    }
    v
}

/// Blocks with their states, previous states and actions.
type Rows = (Vec<Block>, Vec<[f64; 5]>, Vec<[f64; 5]>, Vec<[f64; 2]>);

/// Rows of the true states of `data` at every observed step (one block per step),
/// with the actions that led there.
fn rows(data: &Dataset, model: &impl ParticleModel) -> Rows {
    let states = data.states().expect("ground truth");
    let actions = data.actions().expect("ground truth");
    let (mut blocks, mut now, mut prev, mut acts) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for o in 0..data.objects().len() {
        for t in 1..data.steps() {
            if model.observation_count(o, t) == 0 {
                continue;
            }
            let s = states.get(o, t).expect("state");
            let p = states.get(o, t - 1).expect("state");
            let a = actions.get(o, t).expect("action");
            blocks.push(Block { object: o, t, len: 1 });
            now.push(s.to_array());
            prev.push(p.to_array());
            acts.push([a.accel, a.pinch]);
        }
    }
    (blocks, now, prev, acts)
}

fn columns<'t>(tape: &'t Tape<f64>, rows: &[[f64; 5]], dims: usize) -> Vec<Var<'t, f64>> {
    (0..dims).map(|k| tape.constant(Tensor::from_vec(rows.iter().map(|r| r[k]).collect()))).collect()
}

/// Indicators of a persistent flip's chain for `rows` rows: every `period`-th reversed.
fn flip_bits(rows: usize, period: usize) -> Vec<f64> {
    (0..rows).map(|r| f64::from(u8::from(r % period == 0))).collect()
}

/// `states` with the model's state components beyond the vehicle's five (a
/// persistent flip's indicator) appended as constant columns of `bits`.
fn with_extra_columns<'t>(
    tape: &'t Tape<f64>,
    mut states: Vec<Var<'t, f64>>,
    model: &impl ParticleModel,
    bits: &[f64],
) -> Vec<Var<'t, f64>> {
    for _ in 5..model.state_dim() {
        states.push(tape.constant(Tensor::from_vec(bits.to_vec())));
    }
    states
}

struct Check {
    ext: Extension,
}

impl ModelVisitor for Check {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        let model = ExtendedSsm::new(base, Some(self.ext), &raw(self.ext)).expect("applies");
        let data = model.data();
        let (blocks, now, prev, acts) = rows(data, &model);
        assert!(!blocks.is_empty());

        // The filter's f32 path and the tape's f64 path agree, row by row (a
        // persistent flip's indicator set on every third row).
        let (bits_now, bits_prev) = (flip_bits(now.len(), 3), flip_bits(now.len(), 2));
        let tape = Tape::<f64>::no_record();
        let params = model.bind(&tape);
        let states = with_extra_columns(&tape, columns(&tape, &now, 5), &model, &bits_now);
        let tape_values = model.observation_log_density(&params, &blocks, &states).value().clone();
        // A persistent flip's filter weighs by the marginal over its indicator
        // at the predictive probability q (the state's last component, 0.3
        // here): against the tape's density with the indicator clear and set.
        let q: f64 = 0.3;
        let per_bit = |bit: f64| {
            let bits = vec![bit; now.len()];
            let states = with_extra_columns(&tape, columns(&tape, &now, 5), &model, &bits);
            model.observation_log_density(&params, &blocks, &states).value().clone()
        };
        let (clear, set) = (per_bit(0.0), per_bit(1.0));
        let mut scratch = model.new_scratch();
        for (r, b) in blocks.iter().enumerate() {
            let mut x: Vec<f32> = now[r].iter().map(|&v| v as f32).collect();
            x.resize(model.state_dim(), bits_now[r] as f32);
            let want = if model.flip_chain().is_some() {
                *x.last_mut().unwrap() = q as f32;
                let (a, c) = ((1.0 - q).ln() + clear.data()[r], q.ln() + set.data()[r]);
                a.max(c) + ((a - a.max(c)).exp() + (c - a.max(c)).exp()).ln()
            } else {
                tape_values.data()[r]
            };
            let mut out = [0.0f32];
            assert!(model.observation_loglik(Batch { object: b.object, t: b.t, n: 1 }, &x, &mut out, &mut scratch));
            assert!(
                (out[0] as f64 - want).abs() < 2e-3 * want.abs().max(1.0),
                "{:?} row {r}: f32 {} vs tape {want}",
                self.ext,
                out[0]
            );
        }

        // Tape gradients in the extension's parameter and the states match finite
        // differences (the observation term), and in every parameter for the
        // transition term.
        let theta = model.parameters();
        let ext_index = theta.len() - 1;
        // A small step: the delay's softplus(20 r) is sharply curved.
        let check = GradCheck { step: 1e-5, rel_tol: 1e-5, ..GradCheck::default() };
        let (now_c, prev_c, acts_c) = (now.clone(), prev.clone(), acts.clone());
        let report = check
            .check(
                |tape, vars| {
                    let mut params: Vec<Var<'_, f64>> =
                        theta.iter().map(|p| tape.constant(p.clone())).collect::<Vec<_>>();
                    params[ext_index] = vars[0];
                    let states: Vec<Var<'_, f64>> = (0..5).map(|k| vars[1 + k]).collect();
                    let states = with_extra_columns(tape, states, &model, &bits_now);
                    model.observation_log_density(&params, &blocks, &states).sum()
                },
                &std::iter::once(theta[ext_index].clone())
                    .chain((0..5).map(|k| Tensor::from_vec(now_c.iter().map(|r| r[k]).collect())))
                    .collect::<Vec<_>>(),
            )
            .unwrap_or_else(|e| panic!("{:?}, observation: {e}", self.ext));
        assert!(report.comparisons > 5);
        let report = check
            .check(
                |tape, vars| {
                    let prev = with_extra_columns(tape, columns(tape, &prev_c, 5), &model, &bits_prev);
                    let next = with_extra_columns(tape, columns(tape, &now_c, 5), &model, &bits_now);
                    let a = (0..2)
                        .map(|k| tape.constant(Tensor::from_vec(acts_c.iter().map(|r| r[k]).collect())))
                        .collect::<Vec<_>>();
                    model.transition_log_density(vars, &blocks, &prev, &next, &a).sum()
                },
                &theta,
            )
            .unwrap_or_else(|e| panic!("{:?}, transition: {e}", self.ext));
        assert!(report.comparisons > 5);
    }
}

#[test]
fn plain_and_tape_paths_agree_and_gradients_match_finite_differences() {
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        let d = data(kind);
        for ext in Extension::for_kind(kind) {
            models(kind).visit(&d, Check { ext }).expect("model");
        }
    }
}

struct Inert;

impl ModelVisitor for Inert {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        let data = base.data();
        let plain = ExtendedSsm::new(base, None, &[]).expect("base");
        let (blocks, now, prev, acts) = rows(data, &plain);
        let tape = Tape::<f64>::no_record();
        let states = columns(&tape, &now, 5);
        let base_obs = base.observation_log_density(&base.bind(&tape), &blocks, &states).value().clone();
        let p = columns(&tape, &prev, 5);
        let a =
            (0..2).map(|k| tape.constant(Tensor::from_vec(acts.iter().map(|r| r[k]).collect()))).collect::<Vec<_>>();
        let base_tr = base.transition_log_density(&base.bind(&tape), &blocks, &p, &states, &a).value().clone();
        // No extension: the base model, value for value.
        let same = plain.observation_log_density(&plain.bind(&tape), &blocks, &states).value().clone();
        assert_eq!(same.data(), base_obs.data());
        // An extension at a null value changes nothing (size factors of 1, a fraction
        // of practically 0, a delay of practically 0).
        for ext in Extension::for_kind(O::KIND) {
            let null: Vec<f64> = match ext {
                Extension::SizeBias => vec![0.0, 0.0],
                Extension::Latency => vec![-5.0],
                _ => {
                    let mut v = ext.initial().data().to_vec();
                    v[0] = -5.0; // sigmoid(-40)
                    v
                }
            };
            let model = ExtendedSsm::new(base, Some(ext), &null).expect("applies");
            let params = model.bind(&tape);
            // A persistent flip's indicators all clear: no detection reversed.
            let zeros = vec![0.0; now.len()];
            let states = with_extra_columns(&tape, states.clone(), &model, &zeros);
            let p = with_extra_columns(&tape, p.clone(), &model, &zeros);
            let obs = model.observation_log_density(&params, &blocks, &states).value().clone();
            let tr = model.transition_log_density(&params, &blocks, &p, &states, &a).value().clone();
            for (x, y) in obs.data().iter().zip(base_obs.data()).chain(tr.data().iter().zip(base_tr.data())) {
                assert!((x - y).abs() < 1e-9 * y.abs().max(1.0), "{ext:?}: {x} vs {y}");
            }
        }
    }
}

#[test]
fn extensions_at_their_null_values_are_the_base_model() {
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        models(kind).visit(&data(kind), Inert).expect("model");
    }
}

struct Sampler;

impl ModelVisitor for Sampler {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        // The heavy-tailed sampler: standardised innovations with unit variance and
        // the mixture's excess kurtosis.
        let ext = Extension::HeavyTailedAccel;
        let logit = (0.1f64 / 0.9).ln() / 8.0;
        let ratio = (5.0f64 - 1.0).ln() / 2.0;
        let model = ExtendedSsm::new(base, Some(ext), &[logit, ratio]).expect("applies");
        let state = State { x: 0.0, y: 0.0, yaw: 0.0, v: 8.0, kappa: 0.0 };
        let mut rng = SmallRng::seed_from_u64(4);
        let z: Vec<f64> = (0..200_000)
            .map(|_| {
                let a: Action = model.sample_action(&state, &mut rng);
                model.accel_innovation_of(&state, &a)
            })
            .collect();
        let n = z.len() as f64;
        let mean = z.iter().sum::<f64>() / n;
        let m2 = z.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        let m4 = z.iter().map(|x| (x - mean).powi(4)).sum::<f64>() / n;
        assert!((m2 - 1.0).abs() < 0.02, "variance {m2}");
        let want = mixture_excess_kurtosis(0.1, 5.0);
        assert!((m4 / (m2 * m2) - 3.0 - want).abs() < 0.15 * want, "kurtosis {} vs {want}", m4 / (m2 * m2) - 3.0);
        // Geary's ratio of the draws is the mixture's (the `accel_peakedness` check's statistic).
        assert!((geary_ratio(&z) - mixture_geary(0.1, 5.0)).abs() < 0.005, "Geary {}", geary_ratio(&z));
    }
}

/// Geary's ratio `E|x| / sqrt(E x^2)` of a centred two-normal scale mixture:
/// fraction `p` at `r` times the sd of the rest.
fn mixture_geary(p: f64, r: f64) -> f64 {
    GAUSSIAN_GEARY_RATIO * ((1.0 - p) + p * r) / ((1.0 - p) + p * r * r).sqrt()
}

/// A persistent flip starts at the fraction `yaw_reversal_fraction` measured in
/// excess and the lag-one correlation `yaw_reversal_persistence` measured in
/// excess as its persistence, kept inside [0.05, 0.95]; without a positive
/// excess at the stated 0.5. `heading_flip` reads only the fraction.
#[test]
fn persistent_flip_starts_at_the_runs_the_check_part_measured() {
    let ext = Extension::PersistentFlip;
    let natural = |raw: Tensor<f64>| -> Vec<f64> { ext.natural(raw.data()).unwrap().iter().map(|v| v.1).collect() };
    for (p, lambda) in [(0.2, 0.8), (0.05, 0.3), (0.1, 0.5)] {
        let v = natural(ext.initial_from_checks(&[("yaw_reversal_fraction", p), ("yaw_reversal_persistence", lambda)]));
        assert!((v[0] - p).abs() < 1e-9 && (v[1] - lambda).abs() < 1e-9, "{v:?} for ({p}, {lambda})");
    }
    let v = natural(ext.initial_from_checks(&[("yaw_reversal_fraction", 0.2), ("yaw_reversal_persistence", 1.2)]));
    assert!((v[1] - 0.95).abs() < 1e-9, "clamped: {v:?}");
    for excess in [-0.1, 0.0, f64::NAN] {
        let v =
            natural(ext.initial_from_checks(&[("yaw_reversal_fraction", 0.2), ("yaw_reversal_persistence", excess)]));
        assert!((v[1] - 0.5).abs() < 1e-9, "{excess}: {v:?}");
    }
    let flip = Extension::HeadingFlip;
    assert_eq!(
        flip.initial_from_checks(&[("yaw_reversal_fraction", 0.2), ("yaw_reversal_persistence", 0.1)]),
        flip.initial_from_checks(&[("yaw_reversal_fraction", 0.2)])
    );
    assert_eq!(flip.initial_from_checks(&[]), flip.initial());
}

/// Started from its nested fit, a persistent flip takes the independent flips'
/// fitted fraction and keeps its own persistence; nothing else nests, and values
/// of another length are refused.
#[test]
fn persistent_flip_starts_from_the_independent_flips_fraction() {
    let ext = Extension::PersistentFlip;
    let own = ext.initial_from_checks(&[("yaw_reversal_fraction", 0.2), ("yaw_reversal_persistence", 0.7)]);
    for fraction in [0.03, 0.4] {
        let nested = Extension::HeadingFlip.stored(&[fraction]).unwrap();
        let start = ext.start_from_nested(&nested, &own).expect("persistent flips nest independent ones");
        let v: Vec<f64> = ext.natural(start.data()).unwrap().iter().map(|v| v.1).collect();
        assert!((v[0] - fraction).abs() < 1e-9 && (v[1] - 0.7).abs() < 1e-9, "{v:?} from {fraction}");
    }
    assert!(ext.start_from_nested(&[0.1, 0.2], &own).is_none(), "not heading_flip's values");
    // What that rests on: every nested extension's values are the first of its
    // nesting one's, in the same units.
    for nesting in Extension::ALL {
        let Some(nested) = nesting.nests() else { continue };
        let names =
            |e: Extension| -> Vec<&str> { e.natural(e.initial().data()).unwrap().iter().map(|v| v.0).collect() };
        assert!(names(nesting).starts_with(&names(nested)), "{nesting:?} over {nested:?}");
    }
    for other in [Extension::HeadingFlip, Extension::Clutter, Extension::Latency] {
        assert!(other.start_from_nested(&[0.1], &other.initial()).is_none(), "{other:?} nests nothing");
    }
}

#[test]
fn heavy_tail_start_has_the_peakedness_the_check_part_measured() {
    let ext = Extension::HeavyTailedAccel;
    // Without a kurtosis above the replicates', the start comes from Geary's ratio
    // below them: 5% of draws at the ratio whose mixture has the measured ratio.
    for d in [-0.01, -0.04, -0.1] {
        let raw = ext.initial_from_checks(&[("accel_kurtosis", -0.3), ("accel_peakedness", d)]);
        let v = ext.natural(raw.data()).unwrap();
        let (p, r) = (v[0].1, v[1].1);
        assert!((p - 0.05).abs() < 1e-9, "fraction {p}");
        assert!((mixture_geary(p, r) - (GAUSSIAN_GEARY_RATIO + d)).abs() < 1e-6, "ratio {r} for {d}");
    }
    // A measured kurtosis takes precedence; nothing measured leaves the default start.
    let from_kurtosis = ext.initial_from_checks(&[("accel_kurtosis", 2.0), ("accel_peakedness", -0.1)]);
    assert_eq!(from_kurtosis, ext.initial_from_checks(&[("accel_kurtosis", 2.0)]));
    assert_eq!(ext.initial_from_checks(&[("accel_peakedness", 0.02)]), ext.initial());
    // A Gaussian sample has the Gaussian's ratio.
    let mut rng = SmallRng::seed_from_u64(9);
    let z: Vec<f64> =
        (0..200_000).map(|_| rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng)).collect();
    assert!((geary_ratio(&z) - GAUSSIAN_GEARY_RATIO).abs() < 0.003, "{}", geary_ratio(&z));
}

#[test]
fn heavy_tailed_sampler_has_unit_variance_and_the_mixture_kurtosis() {
    models(ObservationKind::Points).visit(&data(ObservationKind::Points), Sampler).expect("model");
}

struct Defensive;

impl ModelVisitor for Defensive {
    type Output = ();
    fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) {
        let proposal = DefensiveProposal { fraction: 0.1, widening: 8.0 };
        let heavy = [(0.1f64 / 0.9).ln() / 8.0, (5.0f64 - 1.0).ln() / 2.0];
        for (ext, raw) in [(None, &[][..]), (Some(Extension::HeavyTailedAccel), &heavy[..])] {
            let plain = ExtendedSsm::new(base, ext, raw).expect("applies");
            let model = ExtendedSsm::new(base, ext, raw).unwrap().with_proposal(Some(proposal)).unwrap();
            // Particles drawn from the proposal, weighted by transition over
            // proposal, give the transition's expectations: of 1, of z^2 (unit
            // variance) and of the tail mass P(|z| > 3).
            let n = 200_000;
            let state = State { x: 0.0, y: 0.0, yaw: 0.0, v: 8.0, kappa: 0.0 };
            let mut prev = vec![0.0f32; 5 * n];
            for (k, v) in state.to_array().iter().enumerate() {
                prev[k * n..(k + 1) * n].fill(*v as f32);
            }
            let (mut next, mut actions, mut log_w) = (vec![0.0f32; 5 * n], vec![0.0f32; 2 * n], vec![0.0f32; n]);
            let mut scratch = model.new_scratch();
            let mut rng = SmallRng::seed_from_u64(5);
            let to = Drawn { next: &mut next, actions: &mut actions };
            model.propagate(Batch { object: 0, t: 1, n }, &prev, to, &mut rng, &mut scratch);
            assert!(model.proposal_log_weights(n, &mut log_w, &mut scratch));
            let mut plain_scratch = plain.new_scratch();
            assert!(!plain.proposal_log_weights(n, &mut log_w.clone(), &mut plain_scratch), "no proposal, no weights");
            let (mut w_sum, mut w_z2, mut w_tail, mut wide) = (0.0, 0.0, 0.0, 0usize);
            for i in 0..n {
                let a = Action { accel: actions[i] as f64, pinch: actions[n + i] as f64 };
                let z = model.accel_innovation_of(&state, &a);
                let w = (log_w[i] as f64).exp();
                assert!(w.is_finite() && w > 0.0 && w < 1.0 / 0.9 + 1e-4, "weight {w} at z {z}");
                w_sum += w;
                w_z2 += w * z * z;
                w_tail += if z.abs() > 3.0 { w } else { 0.0 };
                wide += usize::from(z.abs() > 8.0);
            }
            let nf = n as f64;
            assert!((w_sum / nf - 1.0).abs() < 0.01, "{ext:?}: mean weight {}", w_sum / nf);
            assert!((w_z2 / nf - 1.0).abs() < 0.03, "{ext:?}: weighted variance {}", w_z2 / nf);
            let tail = match ext {
                // (1 - p) P(|z| > 3 / c) + p P(|z| > 3 / (k c)) for p = 0.1, k = 5, c = 1 / sqrt(3.4).
                Some(_) => 0.9 * two_sided_tail(3.0 * 3.4f64.sqrt()) + 0.1 * two_sided_tail(3.0 * 3.4f64.sqrt() / 5.0),
                None => two_sided_tail(3.0),
            };
            assert!((w_tail / nf - tail).abs() < 0.1 * tail + 5e-4, "{ext:?}: tail {} vs {tail}", w_tail / nf);
            assert!(wide > n / 100, "{ext:?}: the proposal reaches far into the tails ({wide} beyond 8 sd)");
        }

        // Filtering with the proposal estimates the same likelihood: the runs'
        // means agree within their Monte Carlo error.
        let [with, without] = [Some(proposal), None].map(|p| {
            let model = ExtendedSsm::new(base, None, &[]).unwrap().with_proposal(p).unwrap();
            let runs: Vec<f64> = (0..6)
                .map(|seed| {
                    let config = FilterConfig::new(Sampling::new(16384, None), 8, seed);
                    run_filter(&model, &config, |_| ()).log_likelihood()
                })
                .collect();
            let mean = runs.iter().sum::<f64>() / 6.0;
            let var = runs.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / 5.0;
            (mean, var / 6.0)
        });
        let se = (with.1 + without.1).sqrt();
        assert!(
            (with.0 - without.0).abs() < 4.0 * se + 0.5,
            "log-likelihood {with:?} with the proposal, {without:?} without (mean, squared SE)"
        );
        assert!(ExtendedSsm::new(base, None, &[])
            .unwrap()
            .with_proposal(Some(DefensiveProposal { fraction: 1.5, widening: 8.0 }))
            .is_err());
    }
}

/// `P(|z| > x)` for a standard normal `z`.
fn two_sided_tail(x: f64) -> f64 {
    2.0 * ssm::stats::normal_cdf(-x)
}

#[test]
fn defensive_proposal_weights_give_the_transitions_expectations() {
    models(ObservationKind::Points).visit(&data(ObservationKind::Points), Defensive).expect("model");
}

#[test]
fn extensions_apply_to_their_kinds_and_describe_themselves() {
    assert_eq!(Extension::for_kind(ObservationKind::Points).len(), 4);
    assert_eq!(Extension::for_kind(ObservationKind::Boxes).len(), 4);
    assert_eq!(Extension::from_id("latency"), Ok(Extension::Latency));
    assert!(Extension::from_id("wobble").unwrap_err().to_string().contains("heading_flip"));
    let delay = Extension::Latency.describe(&[0.12]).unwrap();
    assert!(delay.starts_with("observations lag the state by 0.12"), "{delay}");
    assert!(Extension::Latency.is_material(&[0.12]).unwrap());
    assert!(!Extension::Latency.is_material(Extension::Latency.initial().data()).unwrap());
    assert!(Extension::Clutter.natural(&[0.0]).is_err(), "wrong length");
    assert!(Extension::Clutter.natural(&[f64::NAN, 0.0]).is_err(), "not finite");
    // Clutter does not apply to detections.
    let d = data(ObservationKind::Boxes);
    struct Refused;
    impl ModelVisitor for Refused {
        type Output = bool;
        fn visit<O: ExtensibleObservation>(self, base: &VehicleSsm<'_, AnyPolicy, O>) -> bool {
            ExtendedSsm::new(base, Some(Extension::Clutter), Extension::Clutter.initial().data()).is_err()
        }
    }
    assert!(models(ObservationKind::Boxes).visit(&d, Refused).unwrap());
}

/// The tempered filter's log-likelihood of box data with reversed headings
/// under `extension` at natural values `natural` (3 runs of 1024 particles):
/// mean and sd over runs.
fn flip_log_likelihood(data: &Dataset, extension: Extension, natural: &[f64]) -> (f64, f64) {
    use ssm::filter::{FilterConfig, Sampling, Tempering};
    use ssm::models::params::FittedExtension;
    use ssm::training::objective::LogLikelihood;
    let mut m = models(ObservationKind::Boxes);
    m.extension = Some(FittedExtension { extension, raw: extension.stored(natural).unwrap() });
    let store = m.to_store();
    let runs: Vec<f64> = (0..3)
        .map(|seed| {
            let config = FilterConfig::new(Sampling::new(1024, Some(Tempering::default())), 8, seed);
            let visit = LogLikelihood { config: &config, extension: Some(extension), params: &store, proposal: None };
            m.visit(data, visit).unwrap().unwrap().0
        })
        .collect();
    let mean = runs.iter().sum::<f64>() / 3.0;
    (mean, (runs.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / 2.0).sqrt())
}

/// Persistent flips of a vanishing persistence are independent flips: on data
/// whose detections are reversed independently (20% and 40%), the filter's
/// log-likelihood under `persistent_flip` at persistence 0.001 is
/// `heading_flip`'s at the same fraction within three sds of the runs (measured
/// 70 and 50 nats lower at sds of 19–29: one more noise component for the
/// tempered filter's moves to carry), and at persistence 0.9 it is clearly
/// lower.
#[test]
fn persistent_flips_without_persistence_filter_as_independent_flips() {
    for (strength, seed) in [(1.0, 21), (2.0, 22)] {
        let effect = HiddenEffect::at_strength("heading_flip", strength).unwrap();
        let config = HiddenConfig { scenes: 3, ..HiddenConfig::quick(ObservationKind::Boxes, effect, seed) };
        let data = generate_hidden(&config).unwrap();
        let fraction = 0.2 * strength;
        let (independent, sd_i) = flip_log_likelihood(&data, Extension::HeadingFlip, &[fraction]);
        let (chain, sd_c) = flip_log_likelihood(&data, Extension::PersistentFlip, &[fraction, 0.001]);
        let (sticky, _) = flip_log_likelihood(&data, Extension::PersistentFlip, &[fraction, 0.9]);
        eprintln!(
            "x{strength}: independent {independent:.2} ({sd_i:.2}), chain {chain:.2} ({sd_c:.2}), sticky {sticky:.2}"
        );
        assert!((chain - independent).abs() < 3.0 * (sd_i + sd_c) + 1.0, "{chain} vs {independent}");
        assert!(sticky < independent - 10.0, "{sticky} vs {independent}");
    }
}

/// A refit's rates (`ObjectiveConfig::base_rate_factor`): the extension's
/// parameter learns at the full rate, every other at the factor. Adam's first
/// step moves each coordinate by its rate (sign of the score), so after one
/// training step the base's coordinates moved at most a tenth of the
/// extension's; without the factor every tensor moves at the rate.
#[test]
fn a_refit_moves_the_base_at_its_rate_and_the_extension_at_the_full_rate() {
    use ssm::estimators::{Estimator, EstimatorConfig};
    use ssm::training::objective::{ObjectiveConfig, SceneObjective};
    use ssm::training::{train, Objective, TrainConfig};
    let kind = ObservationKind::Points;
    let data = data(kind);
    let ext = Extension::HeavyTailedAccel;
    let mut start = models(kind).to_store();
    start.add(&ext.param_name(), ext.initial());
    for factor in [Some(0.1), None] {
        let config = ObjectiveConfig {
            estimator: Estimator::pf_sefi(2),
            estimator_config: EstimatorConfig::new(Sampling::new(32, None)),
            scenes_per_step: 2,
            eval_particles: 32,
            extension: Some(ext),
            extension_only: false,
            frozen: Vec::new(),
            base_rate_factor: factor,
            proposal: None,
            eval_tempering: None,
        };
        let mut objective = SceneObjective::new(&data, data.clone(), config).unwrap();
        let rates = objective.rate_factors(&start);
        let expected: Option<Vec<f64>> =
            factor.map(|f| start.iter().map(|(name, _)| if name == ext.param_name() { 1.0 } else { f }).collect());
        assert_eq!(rates, expected);
        let dir = std::env::temp_dir().join(format!("sefi-refit-rates-{}-{factor:?}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let lr = 0.01;
        let train_config = TrainConfig { lr, epochs: 1, ..TrainConfig::default() };
        let steps = objective.batches();
        assert_eq!(steps, 1, "one batch: one step");
        let outcome = train(&mut objective, start.clone(), &train_config, &dir, false, &mut |_| {}).unwrap();
        let moved = |name: &str| -> f64 {
            let (a, b) = (start.get(start.id(name).unwrap()), outcome.params.get(outcome.params.id(name).unwrap()));
            a.data().iter().zip(b.data()).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
        };
        let ext_name = ext.param_name();
        let ext_moved = moved(&ext_name);
        let base_moved = start.iter().map(|(name, _)| name).filter(|n| *n != ext_name).map(moved).fold(0.0, f64::max);
        let base_rate = lr * factor.unwrap_or(1.0);
        assert!(ext_moved > 0.5 * lr && ext_moved <= lr * (1.0 + 1e-6), "extension moved {ext_moved}");
        assert!(base_moved > 0.5 * base_rate && base_moved <= base_rate * (1.0 + 1e-6), "base moved {base_moved}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

#[test]
fn a_refit_holds_what_its_extension_could_not_have_bent() {
    // Heavy tails act on the dynamics: their refit moves the policy and holds
    // the observation model, every `obs.*` tensor of either kind, and nothing
    // else; every other extension's refit moves every parameter.
    for kind in [ObservationKind::Points, ObservationKind::Boxes] {
        let store = models(kind).to_store();
        let held = RefitScope::Dynamics.held(&store);
        let observation: Vec<String> =
            store.iter().map(|(n, _)| n.to_string()).filter(|n| n.starts_with("obs.")).collect();
        assert!(!held.is_empty() && held == observation, "{kind:?}: {held:?}");
        assert!(store.iter().any(|(n, _)| n.starts_with("policy.") && !held.iter().any(|h| h == n)));
        assert!(RefitScope::All.held(&store).is_empty());
    }
    for ext in Extension::ALL {
        let expected = if ext == Extension::HeavyTailedAccel { RefitScope::Dynamics } else { RefitScope::All };
        assert_eq!(ext.refit_scope(), expected, "{}", ext.id());
        // A nesting pair is compared by object with gains over one reference:
        // both are refitted in one scope.
        if let Some(nested) = ext.nests() {
            assert_eq!(ext.refit_scope(), nested.refit_scope(), "{} and {}", ext.id(), nested.id());
        }
    }
}
