//! The evaluation objects a model does not measure: refined with more particles, and set aside
//! where that does not bring them under the bar.

use super::heldout::{unmeasured_objects, EvalLikelihoods};

use autodiff::nn::ParamStore;

use crate::data::Dataset;
use crate::models::extended::Extension;

use super::config::DiagnoseConfig;
use super::dispatch::eval_likelihoods;
use super::pipeline::Fit;
use super::progress::Stage;
use super::references::Reference;
use super::report::ImpreciseObject;

/// A model compared on the evaluation part: its parameters, its extension, and
/// its likelihoods there.
pub(super) type Compared<'a> = (&'a ParamStore<f64>, Option<Extension>, &'a mut EvalLikelihoods);

/// [`DiagnoseConfig::set_aside_unmeasured`] on the evaluation part `eval`:
/// finds the objects some model (a reference, its reseeded twin, a candidate;
/// `base` the parameters of a reference without a refit) did not measure,
/// filters them again with every model at [`DiagnoseConfig::refine_factor`]
/// times the particles, puts the refined estimates in every model's
/// likelihoods, and marks those still unmeasured to be set aside: the flagged
/// objects, and the indices of those set aside (ascending).
pub(super) fn refine_unmeasured(
    eval: &Dataset,
    base: &ParamStore<f64>,
    references: &mut [Reference],
    fits: &mut [Fit],
    config: &DiagnoseConfig,
    progress: &mut dyn FnMut(&Stage),
) -> Result<(Vec<ImpreciseObject>, Vec<usize>), String> {
    let mut models: Vec<Compared> = Vec::new();
    for r in references.iter_mut() {
        models.push((r.run.as_ref().map_or(base, |run| &run.params), None, &mut r.eval));
        if let Some((again, likelihoods)) = &mut r.reseeded_run {
            models.push((&again.params, None, likelihoods));
        }
    }
    for f in fits.iter_mut() {
        models.push((&f.run.params, Some(f.extension), &mut f.eval));
    }
    let Some(units) = models.first().map(|m| m.2.units) else { return Ok((Vec::new(), Vec::new())) };
    let bar = config.unmeasured_bar(units);
    let unmeasured = |models: &[Compared]| unmeasured_objects(&models.iter().map(|m| &*m.2).collect::<Vec<_>>(), bar);
    let worst = |models: &[Compared], o: usize| models.iter().map(|m| m.2.object_mc_sd[o]).fold(f64::NAN, f64::max);
    let flagged = unmeasured(&models);
    let mut imprecise: Vec<ImpreciseObject> = flagged
        .iter()
        .map(|&o| ImpreciseObject {
            scene: eval.objects()[o].scene,
            id: eval.objects()[o].id,
            units: eval.object_units(o),
            mc_sd: worst(&models, o),
            refined_mc_sd: f64::NAN,
            set_aside: true,
        })
        .collect();
    let refine = DiagnoseConfig { eval_particles: config.eval_particles * config.refine_factor, ..config.clone() };
    if !flagged.is_empty() && config.refine_factor > 1 {
        let subset = eval.select_objects(&flagged);
        let keys: Vec<(i64, i64)> = subset.objects().iter().map(|o| (o.scene, o.id)).collect();
        assert_eq!(keys, imprecise.iter().map(|o| (o.scene, o.id)).collect::<Vec<_>>(), "the subset keeps the order");
        for (i, (params, extension, likelihoods)) in models.iter_mut().enumerate() {
            progress(&Stage::Evaluating {
                model: format!("{} objects refined, model {} of those compared", flagged.len(), i + 1),
            });
            let refined = eval_likelihoods(&subset, params, *extension, &refine)?;
            likelihoods.replace(&flagged, &refined);
        }
        let still = unmeasured(&models);
        for (object, &o) in imprecise.iter_mut().zip(&flagged) {
            object.refined_mc_sd = worst(&models, o);
            object.set_aside = still.binary_search(&o).is_ok();
        }
    }
    let set_aside: Vec<usize> = flagged.iter().zip(&imprecise).filter(|(_, o)| o.set_aside).map(|(&i, _)| i).collect();
    if set_aside.len() == eval.objects().len() {
        return Err(format!(
            "no evaluation object is measured: under some model each one's log-likelihood has a Monte Carlo sd \
             above {bar:.3} nats at {} particles; raise --eval-particles, --eval-runs or --refine-factor (the fits \
             are kept and resume)",
            refine.eval_particles
        ));
    }
    Ok((imprecise, set_aside))
}
