//! Model building blocks over any parameter set: a named parameter store that
//! serialises (versioned, checksummed, written atomically), its binding to a tape,
//! dense layers and MLPs with standard initialisation.
//!
//! ```
//! use autodiff::nn::{Activation, Mlp, ParamStore};
//! use autodiff::{Tape, Tensor};
//! use rand::SeedableRng;
//!
//! let mut rng = rand::rngs::StdRng::seed_from_u64(0);
//! let mut store = ParamStore::<f64>::new();
//! let mlp = Mlp::new(&mut store, "net", &[3, 8, 2], Activation::Tanh, Activation::Identity, &mut rng);
//! assert_eq!(store.num_scalars(), 3 * 8 + 8 + 8 * 2 + 2);
//!
//! let tape = Tape::new();
//! let params = store.bind(&tape);
//! let x = tape.constant(Tensor::zeros(&[5, 3]));
//! let loss = mlp.forward(&params, x).square().sum();
//! let grads = params.gradients(&tape.backward(loss));
//! assert_eq!(grads.len(), store.len());
//! ```

use std::fmt;
use std::io::Write;
use std::path::Path;

use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::float::Float;
use crate::tape::{Gradients, Tape, Var};
use crate::tensor::Tensor;

/// Handle to one parameter tensor in a [`ParamStore`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ParamId(pub usize);

/// An ordered set of named parameter tensors.
///
/// Deserialising checks what [`ParamStore::add`] keeps true: one value per
/// name, and no name twice.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(bound = "F: Float", try_from = "StoreParts<F>")]
pub struct ParamStore<F: Float = f64> {
    names: Vec<String>,
    values: Vec<Tensor<F>>,
}

/// A store's fields as serialised, before [`ParamStore`]'s checks.
#[derive(Deserialize)]
#[serde(bound = "F: Float")]
struct StoreParts<F: Float> {
    names: Vec<String>,
    values: Vec<Tensor<F>>,
}

impl<F: Float> TryFrom<StoreParts<F>> for ParamStore<F> {
    type Error = String;

    fn try_from(parts: StoreParts<F>) -> Result<Self, String> {
        let StoreParts { names, values } = parts;
        if names.len() != values.len() {
            return Err(format!("{} parameter names for {} values", names.len(), values.len()));
        }
        let mut sorted: Vec<&str> = names.iter().map(String::as_str).collect();
        sorted.sort_unstable();
        if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
            return Err(format!("parameter name {:?} given twice", w[0]));
        }
        Ok(ParamStore { names, values })
    }
}

impl<F: Float> Default for ParamStore<F> {
    fn default() -> Self {
        Self::new()
    }
}

/// Errors reading or writing a parameter file.
#[derive(Debug)]
pub enum ParamError {
    /// The file could not be read or written.
    Io {
        /// The file.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The bytes are not a parameter file of this format (bad magic, checksum or
    /// encoding).
    Corrupt {
        /// The file (or `<bytes>`).
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// The file was written by another format version.
    Version {
        /// The file.
        path: String,
        /// Version found in the file.
        found: u32,
    },
    /// A parameter is missing or has the wrong shape for the model.
    Mismatch(String),
}

impl fmt::Display for ParamError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamError::Io { path, source } => write!(f, "{path}: {source}"),
            ParamError::Corrupt { path, reason } => write!(f, "{path}: corrupt parameter file: {reason}"),
            ParamError::Version { path, found } => write!(
                f,
                "{path}: parameter file format version {found}, this program reads version {PARAM_FORMAT_VERSION}"
            ),
            ParamError::Mismatch(m) => write!(f, "parameters do not fit the model: {m}"),
        }
    }
}

impl std::error::Error for ParamError {}

/// First bytes of every file written by [`write_versioned`].
const MAGIC: &[u8; 8] = b"PFSEFI\x00\x01";
/// Version of the parameter store's serialised layout.
pub const PARAM_FORMAT_VERSION: u32 = 1;

/// FNV-1a, 64-bit: a cheap checksum that catches truncation and bit flips.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

/// Serialises `value` with bincode behind a magic number, a format version and a
/// checksum, and writes it atomically (temporary file in the same directory, then
/// rename), so an existing file is never left half-written.
pub fn write_versioned<T: Serialize>(path: &Path, version: u32, value: &T) -> Result<(), ParamError> {
    let io = |source| ParamError::Io { path: path.display().to_string(), source };
    let payload = bincode::serialize(value)
        .map_err(|e| ParamError::Corrupt { path: path.display().to_string(), reason: e.to_string() })?;
    let mut bytes = Vec::with_capacity(payload.len() + 20);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&version.to_le_bytes());
    bytes.extend_from_slice(&fnv1a(&payload).to_le_bytes());
    bytes.extend_from_slice(&payload);
    let tmp = path.with_extension(format!(
        "{}.tmp{}",
        path.extension().and_then(|e| e.to_str()).unwrap_or(""),
        std::process::id()
    ));
    {
        let mut f = std::fs::File::create(&tmp).map_err(io)?;
        f.write_all(&bytes).map_err(io)?;
        f.sync_all().map_err(io)?;
    }
    std::fs::rename(&tmp, path).map_err(io)
}

/// Reads a file written by [`write_versioned`], checking magic, version and checksum.
pub fn read_versioned<T: for<'de> Deserialize<'de>>(path: &Path, version: u32) -> Result<T, ParamError> {
    let p = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| ParamError::Io { path: p.clone(), source })?;
    decode_versioned(&bytes, version, &p)
}

/// Decodes the bytes of a file written by [`write_versioned`] (what
/// [`read_versioned`] does after reading the file), checking magic, version and
/// checksum; `name` names the source in errors (a path, or `<bytes>`).
pub fn decode_versioned<T: for<'de> Deserialize<'de>>(bytes: &[u8], version: u32, name: &str) -> Result<T, ParamError> {
    let corrupt = |reason: &str| ParamError::Corrupt { path: name.to_string(), reason: reason.to_string() };
    if bytes.len() < 20 || &bytes[..8] != MAGIC {
        return Err(corrupt("not a PF-SEFI file (bad header)"));
    }
    let found = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
    if found != version {
        return Err(ParamError::Version { path: name.to_string(), found });
    }
    let sum = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
    let payload = &bytes[20..];
    if fnv1a(payload) != sum {
        return Err(corrupt("checksum mismatch (truncated or damaged)"));
    }
    bincode::deserialize(payload).map_err(|e| corrupt(&e.to_string()))
}

impl<F: Float> ParamStore<F> {
    /// An empty store.
    pub fn new() -> Self {
        ParamStore { names: Vec::new(), values: Vec::new() }
    }

    /// Adds a parameter. Panics if the name is taken (a programming error).
    #[track_caller]
    pub fn add(&mut self, name: &str, value: Tensor<F>) -> ParamId {
        assert!(self.id(name).is_none(), "ParamStore::add: duplicate parameter name {name:?}");
        self.names.push(name.to_string());
        self.values.push(value);
        ParamId(self.values.len() - 1)
    }

    /// The id of a named parameter.
    pub fn id(&self, name: &str) -> Option<ParamId> {
        self.names.iter().position(|n| n == name).map(ParamId)
    }

    /// Number of parameter tensors.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether the store is empty.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Total number of scalar parameters.
    pub fn num_scalars(&self) -> usize {
        self.values.iter().map(|v| v.numel()).sum()
    }

    /// A parameter's value.
    pub fn get(&self, id: ParamId) -> &Tensor<F> {
        &self.values[id.0]
    }

    /// A parameter's value, mutable.
    pub fn get_mut(&mut self, id: ParamId) -> &mut Tensor<F> {
        &mut self.values[id.0]
    }

    /// A parameter's name.
    pub fn name(&self, id: ParamId) -> &str {
        &self.names[id.0]
    }

    /// `(name, value)` pairs in insertion order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Tensor<F>)> {
        self.names.iter().map(|s| s.as_str()).zip(&self.values)
    }

    /// All values, in insertion order.
    pub fn values(&self) -> &[Tensor<F>] {
        &self.values
    }

    /// All values, mutable, in insertion order.
    pub fn values_mut(&mut self) -> &mut [Tensor<F>] {
        &mut self.values
    }

    /// Copies every value into another float type (e.g. f64 master weights to an f32 tape).
    pub fn cast<G: Float>(&self) -> ParamStore<G> {
        ParamStore { names: self.names.clone(), values: self.values.iter().map(|v| v.cast()).collect() }
    }

    /// Puts every parameter on `tape` as a tracked leaf (a constant on a non-recording tape).
    pub fn bind<'t>(&self, tape: &'t Tape<F>) -> BoundParams<'t, F> {
        BoundParams { vars: self.values.iter().map(|v| tape.param(v.clone())).collect() }
    }

    /// Replaces values with those of `other` for every name both share with equal
    /// shapes (e.g. warm-starting an extended model from a base one). Returns how many
    /// were copied.
    pub fn copy_matching(&mut self, other: &ParamStore<F>) -> usize {
        let mut n = 0;
        for (name, v) in other.iter() {
            if let Some(id) = self.id(name) {
                if self.values[id.0].shape() == v.shape() {
                    self.values[id.0] = v.clone();
                    n += 1;
                }
            }
        }
        n
    }

    /// Checks that `other` has exactly this store's names and shapes.
    pub fn check_same_layout(&self, other: &ParamStore<F>) -> Result<(), ParamError> {
        if self.names != other.names {
            return Err(ParamError::Mismatch(format!("expected parameters {:?}, found {:?}", self.names, other.names)));
        }
        for (i, (a, b)) in self.values.iter().zip(&other.values).enumerate() {
            if a.shape() != b.shape() {
                return Err(ParamError::Mismatch(format!(
                    "{}: expected shape {:?}, found {:?}",
                    self.names[i],
                    a.shape(),
                    b.shape()
                )));
            }
        }
        Ok(())
    }

    /// Writes the store atomically to `path` (versioned and checksummed).
    pub fn save(&self, path: &Path) -> Result<(), ParamError> {
        write_versioned(path, PARAM_FORMAT_VERSION, self)
    }

    /// Reads a store written by [`ParamStore::save`].
    pub fn load(path: &Path) -> Result<Self, ParamError> {
        read_versioned(path, PARAM_FORMAT_VERSION)
    }

    /// Decodes the bytes of a file written by [`ParamStore::save`] (what
    /// [`ParamStore::load`] does after reading the file).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ParamError> {
        decode_versioned(bytes, PARAM_FORMAT_VERSION, "<bytes>")
    }
}

/// A parameter store bound to a tape: one leaf per parameter.
pub struct BoundParams<'t, F: Float> {
    vars: Vec<Var<'t, F>>,
}

impl<'t, F: Float> BoundParams<'t, F> {
    /// Wraps leaves that stand for a store's parameters, in store order.
    pub fn from_vars(vars: Vec<Var<'t, F>>) -> Self {
        BoundParams { vars }
    }

    /// The leaf of a parameter.
    pub fn get(&self, id: ParamId) -> Var<'t, F> {
        self.vars[id.0]
    }

    /// The gradient of every parameter, in store order (zeros where unused).
    pub fn gradients(&self, grads: &Gradients<F>) -> Vec<Tensor<F>> {
        self.vars.iter().map(|&v| grads.wrt(v)).collect()
    }
}

/// Element-wise activation of a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Activation {
    /// No activation.
    Identity,
    /// Hyperbolic tangent.
    Tanh,
    /// Rectified linear unit.
    Relu,
    /// ln(1 + e^x).
    Softplus,
    /// Logistic sigmoid.
    Sigmoid,
}

impl Activation {
    /// Applies the activation.
    pub fn apply<'t, F: Float>(self, x: Var<'t, F>) -> Var<'t, F> {
        match self {
            Activation::Identity => x,
            Activation::Tanh => x.tanh(),
            Activation::Relu => x.relu(),
            Activation::Softplus => x.softplus(),
            Activation::Sigmoid => x.sigmoid(),
        }
    }

    /// Standard deviation of the initial weights for `fan_in` inputs and `fan_out`
    /// outputs: He for ReLU, Glorot otherwise.
    fn init_std(self, fan_in: usize, fan_out: usize) -> f64 {
        match self {
            Activation::Relu => (2.0 / fan_in as f64).sqrt(),
            _ => (2.0 / (fan_in + fan_out) as f64).sqrt(),
        }
    }
}

/// A dense layer `act(x W + b)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dense {
    /// Weights `[inputs, outputs]`.
    pub w: ParamId,
    /// Bias `[outputs]`.
    pub b: ParamId,
    /// Activation.
    pub act: Activation,
    /// Input width.
    pub inputs: usize,
    /// Output width.
    pub outputs: usize,
}

impl Dense {
    /// Adds a layer's parameters (`{name}.w`, `{name}.b`) to `store`, with Gaussian
    /// weights scaled for the activation and zero bias.
    pub fn new<F: Float>(
        store: &mut ParamStore<F>,
        name: &str,
        inputs: usize,
        outputs: usize,
        act: Activation,
        rng: &mut impl Rng,
    ) -> Self {
        let normal = Normal::new(0.0, act.init_std(inputs, outputs)).expect("finite std");
        let w: Vec<F> = (0..inputs * outputs).map(|_| F::from_f64(normal.sample(rng))).collect();
        let w = store.add(&format!("{name}.w"), Tensor::new(&[inputs, outputs], w));
        let b = store.add(&format!("{name}.b"), Tensor::zeros(&[outputs]));
        Dense { w, b, act, inputs, outputs }
    }

    /// Applies the layer to `x` of shape `[.., inputs]`.
    pub fn forward<'t, F: Float>(&self, p: &BoundParams<'t, F>, x: Var<'t, F>) -> Var<'t, F> {
        self.act.apply(x.affine(p.get(self.w), p.get(self.b)))
    }
}

/// A multi-layer perceptron: dense layers with one hidden activation and an output
/// activation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Mlp {
    /// The layers, input first.
    pub layers: Vec<Dense>,
}

impl Mlp {
    /// Adds an MLP with layer widths `sizes` (input first, output last) to `store`;
    /// its layers are named `{name}.0`, `{name}.1`, ...
    #[track_caller]
    pub fn new<F: Float>(
        store: &mut ParamStore<F>,
        name: &str,
        sizes: &[usize],
        hidden: Activation,
        output: Activation,
        rng: &mut impl Rng,
    ) -> Self {
        assert!(sizes.len() >= 2, "Mlp::new: need at least input and output sizes, got {sizes:?}");
        let layers = (0..sizes.len() - 1)
            .map(|i| {
                let act = if i + 2 == sizes.len() { output } else { hidden };
                Dense::new(store, &format!("{name}.{i}"), sizes[i], sizes[i + 1], act, rng)
            })
            .collect();
        Mlp { layers }
    }

    /// Applies the network to `x` of shape `[.., inputs]`.
    pub fn forward<'t, F: Float>(&self, p: &BoundParams<'t, F>, x: Var<'t, F>) -> Var<'t, F> {
        self.layers.iter().fold(x, |h, layer| layer.forward(p, h))
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        self.layers.iter().map(|l| l.inputs * l.outputs + l.outputs).sum()
    }
}
