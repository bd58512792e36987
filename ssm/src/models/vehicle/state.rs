//! Vehicle states and actions: one object's values, struct-of-arrays batches (owned
//! and borrowed, for the filter's hot loops) and their counterparts on a tape.
//!
//! State `x = (x, y, yaw, v, kappa)`: position (m), heading (rad), speed (m/s) and
//! curvature (1/m). Action `a = (accel, pinch)`: acceleration (m/s^2) and rate of
//! change of curvature (1/(m s)).

use autodiff::{Float, Var};
use serde::{Deserialize, Serialize};

/// Number of state components.
pub const STATE_DIM: usize = 5;
/// Number of action components.
pub const ACTION_DIM: usize = 2;

/// One vehicle's state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VehicleState<F> {
    /// Position east (m).
    pub x: F,
    /// Position north (m).
    pub y: F,
    /// Heading (rad), not wrapped.
    pub yaw: F,
    /// Speed (m/s).
    pub v: F,
    /// Curvature (1/m), positive turning left.
    pub kappa: F,
}

impl<F: Float> VehicleState<F> {
    /// A state from its components.
    pub fn new(x: F, y: F, yaw: F, v: F, kappa: F) -> Self {
        VehicleState { x, y, yaw, v, kappa }
    }

    /// The components in the order `(x, y, yaw, v, kappa)`.
    pub fn to_array(&self) -> [F; STATE_DIM] {
        [self.x, self.y, self.yaw, self.v, self.kappa]
    }

    /// Converts every component to another float type.
    pub fn cast<G: Float>(&self) -> VehicleState<G> {
        let c = |v: F| G::from_f64(v.to_f64());
        VehicleState::new(c(self.x), c(self.y), c(self.yaw), c(self.v), c(self.kappa))
    }
}

/// One vehicle's action, held constant over a step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Action<F> {
    /// Acceleration (m/s^2).
    pub accel: F,
    /// Rate of change of curvature (1/(m s)).
    pub pinch: F,
}

impl<F: Float> Action<F> {
    /// An action from its components.
    pub fn new(accel: F, pinch: F) -> Self {
        Action { accel, pinch }
    }

    /// Converts every component to another float type.
    pub fn cast<G: Float>(&self) -> Action<G> {
        Action::new(G::from_f64(self.accel.to_f64()), G::from_f64(self.pinch.to_f64()))
    }
}

/// Borrowed struct-of-arrays states (all slices of one length).
#[derive(Clone, Copy, Debug)]
pub struct StatesRef<'a, F> {
    /// Positions east.
    pub x: &'a [F],
    /// Positions north.
    pub y: &'a [F],
    /// Headings.
    pub yaw: &'a [F],
    /// Speeds.
    pub v: &'a [F],
    /// Curvatures.
    pub kappa: &'a [F],
}

/// The length the five components share; panics, naming `what`, if they differ.
#[track_caller]
fn common_len(what: &str, [x, y, yaw, v, kappa]: [usize; 5]) -> usize {
    assert!(
        [y, yaw, v, kappa].iter().all(|&m| m == x),
        "{what}: component lengths differ (x {x}, y {y}, yaw {yaw}, v {v}, kappa {kappa})"
    );
    x
}

impl<F: Float> StatesRef<'_, F> {
    /// Number of states; panics if the slices differ in length.
    #[track_caller]
    pub fn len(&self) -> usize {
        common_len("StatesRef", [self.x.len(), self.y.len(), self.yaw.len(), self.v.len(), self.kappa.len()])
    }

    /// Whether there are no states.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// State `i`.
    pub fn get(&self, i: usize) -> VehicleState<F> {
        VehicleState::new(self.x[i], self.y[i], self.yaw[i], self.v[i], self.kappa[i])
    }
}

/// Mutably borrowed struct-of-arrays states (all slices of one length).
#[derive(Debug)]
pub struct StatesMut<'a, F> {
    /// Positions east.
    pub x: &'a mut [F],
    /// Positions north.
    pub y: &'a mut [F],
    /// Headings.
    pub yaw: &'a mut [F],
    /// Speeds.
    pub v: &'a mut [F],
    /// Curvatures.
    pub kappa: &'a mut [F],
}

impl<F: Float> StatesMut<'_, F> {
    /// Number of states; panics if the slices differ in length.
    #[track_caller]
    pub fn len(&self) -> usize {
        common_len("StatesMut", [self.x.len(), self.y.len(), self.yaw.len(), self.v.len(), self.kappa.len()])
    }

    /// Whether there are no states.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// A shared view of the same states.
    pub fn as_ref(&self) -> StatesRef<'_, F> {
        StatesRef { x: self.x, y: self.y, yaw: self.yaw, v: self.v, kappa: self.kappa }
    }
}

/// Borrowed struct-of-arrays actions (both slices of one length).
#[derive(Clone, Copy, Debug)]
pub struct ActionsRef<'a, F> {
    /// Accelerations.
    pub accel: &'a [F],
    /// Pinches.
    pub pinch: &'a [F],
}

impl<F: Float> ActionsRef<'_, F> {
    /// Number of actions; panics if the slices differ in length.
    #[track_caller]
    pub fn len(&self) -> usize {
        assert_eq!(self.accel.len(), self.pinch.len(), "ActionsRef: accel and pinch lengths differ");
        self.accel.len()
    }

    /// Whether there are no actions.
    pub fn is_empty(&self) -> bool {
        self.accel.is_empty()
    }

    /// Action `i`.
    pub fn get(&self, i: usize) -> Action<F> {
        Action::new(self.accel[i], self.pinch[i])
    }
}

/// Mutably borrowed struct-of-arrays actions (both slices of one length).
#[derive(Debug)]
pub struct ActionsMut<'a, F> {
    /// Accelerations.
    pub accel: &'a mut [F],
    /// Pinches.
    pub pinch: &'a mut [F],
}

impl<F: Float> ActionsMut<'_, F> {
    /// Number of actions; panics if the slices differ in length.
    #[track_caller]
    pub fn len(&self) -> usize {
        assert_eq!(self.accel.len(), self.pinch.len(), "ActionsMut: accel and pinch lengths differ");
        self.accel.len()
    }

    /// Whether there are no actions.
    pub fn is_empty(&self) -> bool {
        self.accel.is_empty()
    }
}

/// Owned struct-of-arrays states.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(bound = "F: Float")]
pub struct StateBatch<F> {
    /// Positions east.
    pub x: Vec<F>,
    /// Positions north.
    pub y: Vec<F>,
    /// Headings.
    pub yaw: Vec<F>,
    /// Speeds.
    pub v: Vec<F>,
    /// Curvatures.
    pub kappa: Vec<F>,
}

impl<F: Float> StateBatch<F> {
    /// `n` zero states.
    pub fn zeros(n: usize) -> Self {
        StateBatch {
            x: vec![F::ZERO; n],
            y: vec![F::ZERO; n],
            yaw: vec![F::ZERO; n],
            v: vec![F::ZERO; n],
            kappa: vec![F::ZERO; n],
        }
    }

    /// The batch holding `states` in order.
    pub fn from_states(states: &[VehicleState<F>]) -> Self {
        let mut b = Self::zeros(states.len());
        for (i, s) in states.iter().enumerate() {
            b.set(i, s);
        }
        b
    }

    /// Number of states.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether there are no states.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Resizes every component to `n` (new entries are zero; no allocation when
    /// shrinking or within capacity).
    pub fn resize(&mut self, n: usize) {
        for c in [&mut self.x, &mut self.y, &mut self.yaw, &mut self.v, &mut self.kappa] {
            c.resize(n, F::ZERO);
        }
    }

    /// State `i`.
    pub fn get(&self, i: usize) -> VehicleState<F> {
        self.view().get(i)
    }

    /// Overwrites state `i`.
    pub fn set(&mut self, i: usize, s: &VehicleState<F>) {
        self.x[i] = s.x;
        self.y[i] = s.y;
        self.yaw[i] = s.yaw;
        self.v[i] = s.v;
        self.kappa[i] = s.kappa;
    }

    /// A borrowed view.
    pub fn view(&self) -> StatesRef<'_, F> {
        StatesRef { x: &self.x, y: &self.y, yaw: &self.yaw, v: &self.v, kappa: &self.kappa }
    }

    /// A mutable borrowed view.
    pub fn view_mut(&mut self) -> StatesMut<'_, F> {
        StatesMut { x: &mut self.x, y: &mut self.y, yaw: &mut self.yaw, v: &mut self.v, kappa: &mut self.kappa }
    }
}

/// Owned struct-of-arrays actions.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(bound = "F: Float")]
pub struct ActionBatch<F> {
    /// Accelerations.
    pub accel: Vec<F>,
    /// Pinches.
    pub pinch: Vec<F>,
}

impl<F: Float> ActionBatch<F> {
    /// `n` zero actions.
    pub fn zeros(n: usize) -> Self {
        ActionBatch { accel: vec![F::ZERO; n], pinch: vec![F::ZERO; n] }
    }

    /// The batch holding `actions` in order.
    pub fn from_actions(actions: &[Action<F>]) -> Self {
        ActionBatch {
            accel: actions.iter().map(|a| a.accel).collect(),
            pinch: actions.iter().map(|a| a.pinch).collect(),
        }
    }

    /// Number of actions.
    pub fn len(&self) -> usize {
        self.accel.len()
    }

    /// Whether there are no actions.
    pub fn is_empty(&self) -> bool {
        self.accel.is_empty()
    }

    /// Resizes both components to `n` (new entries are zero).
    pub fn resize(&mut self, n: usize) {
        self.accel.resize(n, F::ZERO);
        self.pinch.resize(n, F::ZERO);
    }

    /// Action `i`.
    pub fn get(&self, i: usize) -> Action<F> {
        Action::new(self.accel[i], self.pinch[i])
    }

    /// A borrowed view.
    pub fn view(&self) -> ActionsRef<'_, F> {
        ActionsRef { accel: &self.accel, pinch: &self.pinch }
    }

    /// A mutable borrowed view.
    pub fn view_mut(&mut self) -> ActionsMut<'_, F> {
        ActionsMut { accel: &mut self.accel, pinch: &mut self.pinch }
    }
}

/// A batch of states on a tape: one `Var` of shape `[n]` per component.
#[derive(Clone, Copy, Debug)]
pub struct StateVars<'t, F: Float> {
    /// Positions east.
    pub x: Var<'t, F>,
    /// Positions north.
    pub y: Var<'t, F>,
    /// Headings.
    pub yaw: Var<'t, F>,
    /// Speeds.
    pub v: Var<'t, F>,
    /// Curvatures.
    pub kappa: Var<'t, F>,
}

impl<'t, F: Float> StateVars<'t, F> {
    /// Binds a batch as constants on `tape`.
    pub fn constant(tape: &'t autodiff::Tape<F>, states: StatesRef<'_, F>) -> Self {
        let c = |s: &[F]| tape.constant(autodiff::Tensor::from_vec(s.to_vec()));
        StateVars { x: c(states.x), y: c(states.y), yaw: c(states.yaw), v: c(states.v), kappa: c(states.kappa) }
    }

    /// The components in the order `(x, y, yaw, v, kappa)`.
    pub fn to_array(&self) -> [Var<'t, F>; STATE_DIM] {
        [self.x, self.y, self.yaw, self.v, self.kappa]
    }
}

/// A batch of actions on a tape: one `Var` of shape `[n]` per component.
#[derive(Clone, Copy, Debug)]
pub struct ActionVars<'t, F: Float> {
    /// Accelerations.
    pub accel: Var<'t, F>,
    /// Pinches.
    pub pinch: Var<'t, F>,
}

impl<'t, F: Float> ActionVars<'t, F> {
    /// Binds a batch as constants on `tape`.
    pub fn constant(tape: &'t autodiff::Tape<F>, actions: ActionsRef<'_, F>) -> Self {
        ActionVars {
            accel: tape.constant(autodiff::Tensor::from_vec(actions.accel.to_vec())),
            pinch: tape.constant(autodiff::Tensor::from_vec(actions.pinch.to_vec())),
        }
    }
}
