//! The parameter-file convention: one [`ParamStore`] (saved with
//! [`ParamStore::save`]) holds a whole model — policy and observation network —
//! and [`Models::from_store`] rebuilds the models from it.
//!
//! | names | what |
//! |---|---|
//! | `policy.log_sd` (shape `[2]`) | the [`HandCraftedPolicy`]: log sds of accel and pinch |
//! | `policy.0.w`, `policy.0.b`, ... | the [`NeuralPolicy`] network (as [`NeuralPolicy::new`] names it) |
//! | `obs.0.w`, `obs.0.b`, ... | the observation network ([`ObservationModel::init_params`] with prefix `obs`) |
//!
//! The policy is the hand-crafted one exactly when the store has
//! [`HAND_CRAFTED_PARAM`]; otherwise it is the neural one, whose layers must all be
//! present with their shapes. Either way no other `policy.*` name may appear, so a
//! file that mixes the two is rejected rather than silently half-read. The
//! observation network must have exactly the layout of the model for the dataset's
//! kind (points or boxes); a network of the other kind is rejected with a message
//! that says so. A box network whose last layer has the centred width (4
//! outputs, [`DetectionOffsets::Zero`](crate::models::observation::boxes::DetectionOffsets))
//! is read as the centred box model. A catalogue extension learned with the
//! model (`ext.<id>`, [`crate::models::extended`]; at most one, of the right
//! shape, for the dataset's kind) is read into [`Models::extension`], a
//! detector drift (`drift`, [`crate::models::drift`]; box data only) into
//! [`Models::drift`]. Other names (optimiser state) are ignored.
//!
//! ```
//! use autodiff::nn::ParamStore;
//! use rand::SeedableRng;
//! use ssm::data::ObservationKind;
//! use ssm::models::observation::{ObservationModel, PointObservationModel, OBS_PREFIX};
//! use ssm::models::params::{AnyPolicy, Models};
//! use ssm::models::vehicle::HandCraftedPolicy;
//!
//! let mut store = ParamStore::new();
//! AnyPolicy::HandCrafted(HandCraftedPolicy::truth()).add_to_store(&mut store);
//! PointObservationModel::init_params(&mut store, OBS_PREFIX, &mut rand::rngs::StdRng::seed_from_u64(0));
//! let models = Models::from_store(&store, ObservationKind::Points).unwrap();
//! assert!(matches!(models.policy, AnyPolicy::HandCrafted(_)));
//! // The same file cannot drive a box-detection model.
//! assert!(Models::from_store(&store, ObservationKind::Boxes).is_err());
//! ```

use std::fmt;

use autodiff::nn::ParamStore;
use autodiff::{Float, Tape, Tensor, Var};
use rand::rngs::StdRng;
use rand::SeedableRng;

use crate::data::{Dataset, ObservationKind};
use crate::models::drift::{DetectorDrift, DRIFT_PARAM};
use crate::models::extended::{ExtendedSsm, ExtensibleObservation, Extension, EXTENSION_PREFIX};
use crate::models::observation::boxes::DetectionOffsets;
use crate::models::observation::{BoxObservationModel, ObservationModel, PointObservationModel, OBS_PREFIX};
use crate::models::road_user::VehicleSsm;
use crate::models::vehicle::policy::{ActionGaussianVars, ActionGaussians, GaussianPolicy, PolicyError};
use crate::models::vehicle::{HandCraftedPolicy, NeuralPolicy};
use crate::models::ModelError;

/// Name prefix of the policy's parameters.
pub const POLICY_PREFIX: &str = "policy";
pub use crate::models::vehicle::policy::HAND_CRAFTED_PARAM;

/// What is wrong with a parameter store.
#[derive(Clone, Debug, PartialEq)]
pub enum ParamsError {
    /// No `policy.*` parameter at all.
    NoPolicy,
    /// No `obs.*` parameter at all.
    NoObservation,
    /// A parameter the model needs is missing.
    Missing {
        /// Its name.
        name: String,
        /// What the model is.
        model: String,
    },
    /// A parameter has the wrong shape.
    Shape {
        /// Its name.
        name: String,
        /// The shape the model needs.
        expected: Vec<usize>,
        /// The shape in the store.
        found: Vec<usize>,
        /// What the model is.
        model: String,
    },
    /// A parameter under a model's prefix that the model does not have.
    Unexpected {
        /// Its name.
        name: String,
        /// What the model is.
        model: String,
    },
    /// A parameter holds NaN or an infinity.
    NonFinite {
        /// Its name.
        name: String,
    },
}

impl fmt::Display for ParamsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamsError::NoPolicy => write!(
                f,
                "no policy parameters: expected `{HAND_CRAFTED_PARAM}` (hand-crafted policy) \
                 or `{POLICY_PREFIX}.0.w`, ... (neural policy)"
            ),
            ParamsError::NoObservation => {
                write!(f, "no observation-network parameters: expected `{OBS_PREFIX}.0.w`, `{OBS_PREFIX}.0.b`, ...")
            }
            ParamsError::Missing { name, model } => write!(f, "parameter `{name}` of the {model} is missing"),
            ParamsError::Shape { name, expected, found, model } => {
                write!(f, "parameter `{name}` has shape {found:?}; the {model} needs {expected:?}")
            }
            ParamsError::Unexpected { name, model } => write!(f, "parameter `{name}` is not part of the {model}"),
            ParamsError::NonFinite { name } => write!(f, "parameter `{name}` holds a non-finite value"),
        }
    }
}

impl std::error::Error for ParamsError {}

/// Either policy, so code generic over [`GaussianPolicy`] runs with whichever a
/// parameter file holds.
#[derive(Clone, Debug, PartialEq)]
pub enum AnyPolicy {
    /// The hand-crafted policy of the synthetic data.
    HandCrafted(HandCraftedPolicy),
    /// The neural policy of the measured data.
    Neural(NeuralPolicy),
}

impl AnyPolicy {
    /// A short name: `hand-crafted` or `neural`.
    pub fn name(&self) -> &'static str {
        match self {
            AnyPolicy::HandCrafted(_) => "hand-crafted",
            AnyPolicy::Neural(_) => "neural",
        }
    }

    /// Adds the policy's parameters to `store` under the convention of the
    /// [module docs](self). Panics if a name is taken (a programming error).
    #[track_caller]
    pub fn add_to_store(&self, store: &mut ParamStore<f64>) {
        match self {
            AnyPolicy::HandCrafted(p) => {
                store.add(HAND_CRAFTED_PARAM, Tensor::from_vec(vec![p.log_sd_accel(), p.log_sd_pinch()]));
            }
            AnyPolicy::Neural(p) => {
                for (name, value) in p.store().iter() {
                    store.add(name, value.clone());
                }
            }
        }
    }

    /// Reads the policy from `store` (see the [module docs](self)).
    pub fn from_store(store: &ParamStore<f64>) -> Result<AnyPolicy, ParamsError> {
        let prefix = format!("{POLICY_PREFIX}.");
        let names: Vec<&str> = store.iter().map(|(n, _)| n).filter(|n| n.starts_with(&prefix)).collect();
        if names.is_empty() {
            return Err(ParamsError::NoPolicy);
        }
        if let Some(id) = store.id(HAND_CRAFTED_PARAM) {
            let model = "hand-crafted policy".to_string();
            if let Some(other) = names.iter().find(|&&n| n != HAND_CRAFTED_PARAM) {
                return Err(ParamsError::Unexpected { name: other.to_string(), model });
            }
            let v = store.get(id);
            if v.shape() != [2] {
                return Err(ParamsError::Shape {
                    name: HAND_CRAFTED_PARAM.into(),
                    expected: vec![2],
                    found: v.shape().to_vec(),
                    model,
                });
            }
            check_finite(HAND_CRAFTED_PARAM, v)?;
            let p = HandCraftedPolicy::new(v.data()[0], v.data()[1])
                .map_err(|_| ParamsError::NonFinite { name: HAND_CRAFTED_PARAM.into() })?;
            return Ok(AnyPolicy::HandCrafted(p));
        }
        let mut policy = NeuralPolicy::new(&mut StdRng::seed_from_u64(0));
        copy_exact(policy.store_mut(), store, POLICY_PREFIX, "neural policy")?;
        Ok(AnyPolicy::Neural(policy))
    }
}

impl GaussianPolicy for AnyPolicy {
    fn parameters(&self) -> Vec<Tensor<f64>> {
        match self {
            AnyPolicy::HandCrafted(p) => p.parameters(),
            AnyPolicy::Neural(p) => p.parameters(),
        }
    }

    fn parameter_names(&self) -> Vec<String> {
        match self {
            AnyPolicy::HandCrafted(p) => p.parameter_names(),
            AnyPolicy::Neural(p) => p.parameter_names(),
        }
    }

    fn set_parameters(&mut self, params: &[Tensor<f64>]) -> Result<(), PolicyError> {
        match self {
            AnyPolicy::HandCrafted(p) => p.set_parameters(params),
            AnyPolicy::Neural(p) => p.set_parameters(params),
        }
    }

    fn gaussians<F: Float>(&self, v: &[F], kappa: &[F], out: &mut ActionGaussians<F>) {
        match self {
            AnyPolicy::HandCrafted(p) => p.gaussians(v, kappa, out),
            AnyPolicy::Neural(p) => p.gaussians(v, kappa, out),
        }
    }

    fn gaussians_on_tape<'t, F: Float>(
        &self,
        params: &[Var<'t, F>],
        v: Var<'t, F>,
        kappa: Var<'t, F>,
    ) -> ActionGaussianVars<'t, F> {
        match self {
            AnyPolicy::HandCrafted(p) => p.gaussians_on_tape(params, v, kappa),
            AnyPolicy::Neural(p) => p.gaussians_on_tape(params, v, kappa),
        }
    }

    fn bind_parameters<'t, F: Float>(&self, tape: &'t Tape<F>) -> Vec<Var<'t, F>> {
        match self {
            AnyPolicy::HandCrafted(p) => p.bind_parameters(tape),
            AnyPolicy::Neural(p) => p.bind_parameters(tape),
        }
    }
}

/// Either observation model (the trait has an item type, so it is not itself an
/// object; [`AnyObservation::visit`] runs code generic over the model).
#[derive(Clone, Debug, PartialEq)]
pub enum AnyObservation {
    /// Point sets.
    Points(PointObservationModel),
    /// Box detections.
    Boxes(BoxObservationModel),
}

impl AnyObservation {
    /// A fresh model for a dataset of `kind`, its network added to `store` under
    /// [`OBS_PREFIX`] with standard initialisation drawn from `rng`.
    pub fn init(kind: ObservationKind, store: &mut ParamStore<f64>, rng: &mut StdRng) -> AnyObservation {
        AnyObservation::init_with_offsets(kind, DetectionOffsets::Learned, store, rng)
    }

    /// [`AnyObservation::init`], with the box model's detection offsets learned or
    /// fixed at zero (`offsets` is ignored for points).
    pub fn init_with_offsets(
        kind: ObservationKind,
        offsets: DetectionOffsets,
        store: &mut ParamStore<f64>,
        rng: &mut StdRng,
    ) -> AnyObservation {
        match kind {
            ObservationKind::Points => {
                AnyObservation::Points(PointObservationModel::init_params(store, OBS_PREFIX, rng))
            }
            ObservationKind::Boxes => {
                AnyObservation::Boxes(BoxObservationModel::init_with_offsets(store, OBS_PREFIX, offsets, rng))
            }
        }
    }

    /// The kind of dataset the model reads.
    pub fn kind(&self) -> ObservationKind {
        match self {
            AnyObservation::Points(_) => ObservationKind::Points,
            AnyObservation::Boxes(_) => ObservationKind::Boxes,
        }
    }

    /// Hands the model, of whichever kind, to `visitor` (which is generic over the
    /// observation model): the one place that dispatches on the kind.
    pub fn visit<V: ObservationVisitor>(&self, visitor: V) -> V::Output {
        match self {
            AnyObservation::Points(o) => visitor.visit(o),
            AnyObservation::Boxes(o) => visitor.visit(o),
        }
    }
}

/// Code generic over the observation model, run by [`AnyObservation::visit`].
pub trait ObservationVisitor {
    /// What the visit returns.
    type Output;
    /// Runs on the model.
    fn visit<O: ExtensibleObservation>(self, model: &O) -> Self::Output;
}

/// Code generic over the vehicle model of a dataset, run by [`Models::visit`].
pub trait ModelVisitor {
    /// What the visit returns.
    type Output;
    /// Runs on the model.
    fn visit<O: ExtensibleObservation>(self, model: &VehicleSsm<'_, AnyPolicy, O>) -> Self::Output;
}

/// A policy and an observation model with its parameters, read from one store.
#[derive(Clone, Debug)]
pub struct Models {
    /// The policy (its parameters inside).
    pub policy: AnyPolicy,
    /// The observation model (a layout referring to `observation_params`).
    pub observation: AnyObservation,
    /// The observation network's parameters, laid out as `observation` expects.
    pub observation_params: ParamStore<f64>,
    /// The catalogue extension learned with the model, if any (`sefi train
    /// --extension`): filters, likelihoods and AOTLL use the extended model.
    pub extension: Option<FittedExtension>,
    /// The detector drift learned with the model, if any (`sefi train --drift`):
    /// its stored values ([`DetectorDrift::from_raw`]).
    pub drift: Option<Vec<f64>>,
}

/// A catalogue extension with its stored values, as a parameter file holds it
/// (`ext.<id>`).
#[derive(Clone, Debug, PartialEq)]
pub struct FittedExtension {
    /// The catalogue entry.
    pub extension: Extension,
    /// Its stored (scaled) values; [`Extension::natural`] gives them in units.
    pub raw: Vec<f64>,
}

impl FittedExtension {
    /// The extension `store` holds for data of `kind`, if any. Fails on an
    /// unknown id, a second extension, one that means nothing for `kind`, a wrong
    /// shape or a value that is not finite, naming the parameter.
    pub fn from_store(store: &ParamStore<f64>, kind: ObservationKind) -> Result<Option<Self>, ParamsError> {
        let prefix = format!("{EXTENSION_PREFIX}.");
        let mut found: Option<FittedExtension> = None;
        for (name, value) in store.iter().filter(|(n, _)| n.starts_with(&prefix)) {
            let unexpected = |model: String| ParamsError::Unexpected { name: name.to_string(), model };
            let extension = Extension::from_id(&name[prefix.len()..])
                .map_err(|_| unexpected("catalogue of model extensions".into()))?;
            if let Some(other) = &found {
                return Err(unexpected(format!("model extended by {} (at most one extension)", other.extension.id())));
            }
            if !extension.applies_to(kind) {
                return Err(unexpected(format!("model of {kind:?} observations")));
            }
            let expected = extension.initial().shape().to_vec();
            if value.shape() != expected.as_slice() {
                let model = format!("{} extension", extension.id());
                return Err(ParamsError::Shape {
                    name: name.to_string(),
                    expected,
                    found: value.shape().to_vec(),
                    model,
                });
            }
            check_finite(name, value)?;
            found = Some(FittedExtension { extension, raw: value.data().to_vec() });
        }
        Ok(found)
    }
}

/// What a parameter file adds to the base vehicle model: a catalogue
/// extension and a detector drift, each if learned ([`Models::additions`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct ModelAdditions<'e> {
    /// The catalogue extension, if any.
    pub extension: Option<&'e FittedExtension>,
    /// The detector drift's stored values, if any.
    pub drift: Option<&'e [f64]>,
}

impl<'e> ModelAdditions<'e> {
    /// The base model alone.
    pub const NONE: ModelAdditions<'static> = ModelAdditions { extension: None, drift: None };

    /// A catalogue extension (if any) and no drift.
    pub fn extension(extension: Option<&'e FittedExtension>) -> Self {
        ModelAdditions { extension, drift: None }
    }

    /// `base` with these additions. Fails where one does not apply to the data.
    pub fn extend<'m, 'a, P: GaussianPolicy, O: ExtensibleObservation>(
        self,
        base: &'m VehicleSsm<'a, P, O>,
    ) -> Result<ExtendedSsm<'m, 'a, P, O>, ModelError> {
        let (ext, raw) = self.extension.map_or((None, &[][..]), |e| (Some(e.extension), e.raw.as_slice()));
        ExtendedSsm::new(base, ext, raw)?.with_drift(self.drift)
    }
}

impl Models {
    /// The extension and drift these models hold.
    pub fn additions(&self) -> ModelAdditions<'_> {
        ModelAdditions { extension: self.extension.as_ref(), drift: self.drift.as_deref() }
    }

    /// Fresh models to learn from, for a dataset of `kind`: the given policy and an
    /// observation network with standard initialisation drawn from `seed`.
    pub fn initial(kind: ObservationKind, policy: AnyPolicy, seed: u64) -> Models {
        Models::initial_with_offsets(kind, policy, seed, DetectionOffsets::Learned)
    }

    /// [`Models::initial`] with the box model's detection offsets learned or fixed
    /// at zero ([`DetectionOffsets`]; ignored for points).
    pub fn initial_with_offsets(
        kind: ObservationKind,
        policy: AnyPolicy,
        seed: u64,
        offsets: DetectionOffsets,
    ) -> Models {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut observation_params = ParamStore::new();
        let observation = AnyObservation::init_with_offsets(kind, offsets, &mut observation_params, &mut rng);
        Models { policy, observation, observation_params, extension: None, drift: None }
    }

    /// Reads the policy and the observation model for a dataset of `kind` from
    /// `store` (see the [module docs](self)).
    pub fn from_store(store: &ParamStore<f64>, kind: ObservationKind) -> Result<Models, ParamsError> {
        let policy = AnyPolicy::from_store(store)?;
        let prefix = format!("{OBS_PREFIX}.");
        if !store.iter().any(|(n, _)| n.starts_with(&prefix)) {
            return Err(ParamsError::NoObservation);
        }
        let mut observation_params = ParamStore::new();
        let mut rng = StdRng::seed_from_u64(0);
        let offsets = BoxObservationModel::offsets_in_store(store, OBS_PREFIX);
        let observation = AnyObservation::init_with_offsets(kind, offsets, &mut observation_params, &mut rng);
        let model = match kind {
            ObservationKind::Points => "point observation model (this dataset holds points.csv)",
            ObservationKind::Boxes => "box-detection observation model (this dataset holds boxes.csv)",
        };
        copy_exact(&mut observation_params, store, OBS_PREFIX, model)?;
        let extension = FittedExtension::from_store(store, kind)?;
        let drift = drift_in_store(store, kind)?;
        Ok(Models { policy, observation, observation_params, extension, drift })
    }

    /// Builds the [`VehicleSsm`] of `data` under these models and hands it to
    /// `visitor` (which is generic over the observation model). Fails if the
    /// dataset's kind is not the one the observation model reads.
    pub fn visit<V: ModelVisitor>(&self, data: &Dataset, visitor: V) -> Result<V::Output, ModelError> {
        /// The [`VehicleSsm`] of the visited observation model, handed to `visitor`.
        struct Ssm<'a, V> {
            data: &'a Dataset,
            models: &'a Models,
            visitor: V,
        }
        impl<V: ModelVisitor> ObservationVisitor for Ssm<'_, V> {
            type Output = Result<V::Output, ModelError>;
            fn visit<O: ExtensibleObservation>(self, o: &O) -> Self::Output {
                let (p, params) = (&self.models.policy, &self.models.observation_params);
                Ok(self.visitor.visit(&VehicleSsm::new(self.data, p, o, params)?))
            }
        }
        self.observation.visit(Ssm { data, models: self, visitor })
    }

    /// A store holding these models under the convention of the [module docs](self)
    /// (what [`Models::from_store`] reads back).
    pub fn to_store(&self) -> ParamStore<f64> {
        let mut store = ParamStore::new();
        self.policy.add_to_store(&mut store);
        for (name, value) in self.observation_params.iter() {
            store.add(name, value.clone());
        }
        if let Some(e) = &self.extension {
            store.add(&e.extension.param_name(), Tensor::from_vec(e.raw.clone()));
        }
        if let Some(raw) = &self.drift {
            store.add(DRIFT_PARAM, Tensor::from_vec(raw.clone()));
        }
        store
    }
}

/// The detector drift `store` holds ([`DRIFT_PARAM`]) for data of `kind`, if
/// any. Fails on data other than boxes, a wrong shape or a value that is not
/// finite, naming the parameter.
pub fn drift_in_store(store: &ParamStore<f64>, kind: ObservationKind) -> Result<Option<Vec<f64>>, ParamsError> {
    let Some(id) = store.id(DRIFT_PARAM) else { return Ok(None) };
    let model = "detector drift".to_string();
    if kind != ObservationKind::Boxes {
        return Err(ParamsError::Unexpected {
            name: DRIFT_PARAM.into(),
            model: format!("model of {kind:?} observations"),
        });
    }
    let (value, expected) = (store.get(id), DetectorDrift::initial().shape().to_vec());
    if value.shape() != expected.as_slice() {
        return Err(ParamsError::Shape { name: DRIFT_PARAM.into(), expected, found: value.shape().to_vec(), model });
    }
    check_finite(DRIFT_PARAM, value)?;
    Ok(Some(value.data().to_vec()))
}

fn check_finite(name: &str, v: &Tensor<f64>) -> Result<(), ParamsError> {
    if v.data().iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(ParamsError::NonFinite { name: name.into() })
    }
}

/// Fills every parameter of `target` from `source`, requiring the `prefix.*`
/// names of `source` to be exactly those of `target`, with equal shapes.
fn copy_exact(
    target: &mut ParamStore<f64>,
    source: &ParamStore<f64>,
    prefix: &str,
    model: &str,
) -> Result<(), ParamsError> {
    let dotted = format!("{prefix}.");
    for (name, _) in source.iter().filter(|(n, _)| n.starts_with(&dotted)) {
        if target.id(name).is_none() {
            return Err(ParamsError::Unexpected { name: name.into(), model: model.into() });
        }
    }
    for i in 0..target.len() {
        let id = autodiff::nn::ParamId(i);
        let name = target.name(id).to_string();
        let Some(src) = source.id(&name) else {
            return Err(ParamsError::Missing { name, model: model.into() });
        };
        let value = source.get(src);
        if value.shape() != target.get(id).shape() {
            return Err(ParamsError::Shape {
                expected: target.get(id).shape().to_vec(),
                found: value.shape().to_vec(),
                name,
                model: model.into(),
            });
        }
        check_finite(&name, value)?;
        *target.get_mut(id) = value.clone();
    }
    Ok(())
}
