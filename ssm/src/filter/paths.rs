//! Paths drawn from the particle filter's genealogy: [`PathRecorder`] records one
//! object's filter steps (with the tempered filter's revisions of the previous
//! step) and, at the last, draws whole state and action paths with the final
//! weights — the particle approximation of the smoother that the diagnosis's
//! posterior predictive checks sample from.

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};

use super::{Observer, StepView};
use crate::data::{Action, State};
use crate::models::extended::state_at;

/// Records one object's filter steps and, at the last, draws paths from the
/// genealogy with the final weights (the particle approximation of the smoother).
pub struct PathRecorder {
    steps: usize,
    draws: usize,
    seed: u64,
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    parents: Vec<Vec<usize>>,
    /// The drawn paths (filled at the last step): states `x_0..x_T` and actions
    /// `a_1..a_T`.
    pub paths: Vec<(Vec<State>, Vec<Action>)>,
}

impl PathRecorder {
    /// A recorder of an object with `steps` steps that will draw `draws` paths
    /// with randomness from `seed`.
    pub fn new(steps: usize, draws: usize, seed: u64) -> Self {
        PathRecorder {
            steps,
            draws,
            seed,
            states: Vec::with_capacity(steps),
            actions: Vec::with_capacity(steps),
            parents: Vec::with_capacity(steps),
            paths: Vec::new(),
        }
    }
}

impl Observer for PathRecorder {
    fn step(&mut self, view: &StepView<'_>) {
        for (s, step) in view.revised_earlier.iter().enumerate() {
            self.states[s] = step.states.to_vec();
            self.actions[s] = step.actions.to_vec();
            self.parents[s] = step.parents.to_vec();
        }
        if let Some(parent) = &view.revised_parent {
            let t = view.t;
            self.states[t - 1] = parent.states.to_vec();
            self.actions[t - 1] = parent.actions.to_vec();
            self.parents[t - 1] = parent.parents.to_vec();
        }
        self.states.push(view.states.to_vec());
        self.actions.push(view.actions.to_vec());
        self.parents.push(view.parents.to_vec());
        if view.t + 1 < self.steps {
            return;
        }
        let n = view.n;
        let weights: Vec<f64> = view.log_weights.iter().map(|l| l.exp()).collect();
        let total: f64 = weights.iter().sum();
        let mut rng = SmallRng::seed_from_u64(self.seed);
        for _ in 0..self.draws {
            let mut u = rng.random::<f64>() * total;
            let mut i = n - 1;
            for (j, w) in weights.iter().enumerate() {
                if u < *w {
                    i = j;
                    break;
                }
                u -= w;
            }
            let mut states = vec![State::default(); self.steps];
            let mut actions = vec![Action::default(); self.steps - 1];
            for t in (0..self.steps).rev() {
                states[t] = state_at(&self.states[t], n, i);
                if t > 0 {
                    let a = &self.actions[t];
                    actions[t - 1] = Action { accel: a[i] as f64, pinch: a[n + i] as f64 };
                    i = self.parents[t][i];
                }
            }
            self.paths.push((states, actions));
        }
        // The genealogy is no longer needed: free it.
        self.states = Vec::new();
        self.actions = Vec::new();
        self.parents = Vec::new();
    }
}
