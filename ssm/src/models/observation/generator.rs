//! The physically motivated point generator of the synthetic data (SPEC §4): what
//! a LiDAR sees of a box, used to make labelled examples from which the "true"
//! point-observation network is fitted ([`super::fit`]).
//!
//! Given the object's pose and extents and the AV's pose:
//!
//! * **How many points**: Poisson with mean `min(count_scale / range, max_mean_count)`
//!   (300 / r capped at 40 by default: 40 at 5 m, 15 at 20 m, 6 at 50 m).
//! * **Which edges**: only edges facing the AV (the AV is on the outward side of
//!   the edge's line), each with probability proportional to its apparent size,
//!   `len_e * cos(incidence_e)` — the edge's length times the cosine between its
//!   outward normal and the direction from its midpoint to the AV. An edge seen
//!   head-on gets the most points, one seen at a grazing angle almost none.
//! * **Where on the edge**: uniform along it, plus Gaussian jitter
//!   (`along_noise`, 3 cm).
//! * **Noise across the edge**: Gaussian with sd `noise_base + noise_per_metre * range`
//!   (3 cm + 4 mm per metre: 5 cm at 5 m, 23 cm at 50 m).
//!
//! The noise is Gaussian where the model's is Laplace, and the edge weights depend
//! on the geometry in a way the network must learn: the fitted network
//! approximates the generator, as a learned observation model approximates a
//! sensor.

use std::f64::consts::TAU;

use rand::Rng;
use rand_distr::{Distribution, Normal, Poisson};

use super::edges::{edge_lengths, edge_point, from_box_frame, NUM_EDGES};
use super::fit::Example;
use super::ObsContext;
use crate::data::Pose;

/// The point generator's settings (see the [module docs](self)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointGenerator {
    /// Mean number of points at range `r` is `count_scale / r` (m)...
    pub count_scale: f64,
    /// ... capped at this.
    pub max_mean_count: f64,
    /// Sd of the outward offset at range 0 (m).
    pub noise_base: f64,
    /// Growth of that sd per metre of range.
    pub noise_per_metre: f64,
    /// Sd of the jitter along an edge (m).
    pub along_noise: f64,
}

impl Default for PointGenerator {
    fn default() -> Self {
        PointGenerator {
            count_scale: 300.0,
            max_mean_count: 40.0,
            noise_base: 0.03,
            noise_per_metre: 0.004,
            along_noise: 0.03,
        }
    }
}

/// Range of the object from the AV (m).
fn range(ctx: &ObsContext, pose: Pose) -> f64 {
    (pose.x - ctx.av.x).hypot(pose.y - ctx.av.y)
}

impl PointGenerator {
    /// Mean number of points at `range` (m).
    pub fn mean_count(&self, range: f64) -> f64 {
        (self.count_scale / range.max(1e-9)).min(self.max_mean_count)
    }

    /// Sd of the outward offset at `range` (m).
    pub fn noise_sd(&self, range: f64) -> f64 {
        self.noise_base + self.noise_per_metre * range
    }

    /// Probability of each edge (0 front, 1 left, 2 rear, 3 right): proportional to
    /// the apparent size of the edges facing the AV, zero for the others. If the AV
    /// faces no edge (it is inside the box), proportional to the edge lengths.
    ///
    /// ```
    /// use ssm::data::Pose;
    /// use ssm::models::observation::{ObsContext, PointGenerator};
    /// // AV 20 m straight behind a car: only the rear is seen.
    /// let ctx = ObsContext::new(Pose { x: -20.0, y: 0.0, yaw: 0.0 }, 4.5, 1.8);
    /// let w = PointGenerator::default().edge_weights(&ctx, Pose { x: 0.0, y: 0.0, yaw: 0.0 });
    /// assert_eq!(w, [0.0, 0.0, 1.0, 0.0]);
    /// ```
    pub fn edge_weights(&self, ctx: &ObsContext, pose: Pose) -> [f64; NUM_EDGES] {
        let (c, s) = (pose.yaw.cos(), pose.yaw.sin());
        let (hl, hw) = (0.5 * ctx.length, 0.5 * ctx.width);
        let lens = edge_lengths(ctx.length, ctx.width);
        // Outward normals and midpoints (box frame) of edges 0..4.
        let normals = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)];
        let mids = [(hl, 0.0), (0.0, hw), (-hl, 0.0), (0.0, -hw)];
        // The AV in the box frame.
        let (dx, dy) = (ctx.av.x - pose.x, ctx.av.y - pose.y);
        let (au, av) = (c * dx + s * dy, c * dy - s * dx);
        let mut w = [0.0; NUM_EDGES];
        for e in 0..NUM_EDGES {
            let (tu, tv) = (au - mids[e].0, av - mids[e].1);
            let dist = tu.hypot(tv);
            let cos_inc = (normals[e].0 * tu + normals[e].1 * tv) / dist.max(1e-12);
            w[e] = lens[e] * cos_inc.max(0.0);
        }
        let total: f64 = w.iter().sum();
        if total > 0.0 {
            w.map(|x| x / total)
        } else {
            let t: f64 = lens.iter().sum();
            lens.map(|x| x / t)
        }
    }

    /// Appends exactly `n` points to `out`, with their edges if `edges` is given.
    pub fn sample_n<R: Rng + ?Sized>(
        &self,
        ctx: &ObsContext,
        pose: Pose,
        n: usize,
        rng: &mut R,
        out: &mut Vec<[f64; 2]>,
        mut edges: Option<&mut Vec<usize>>,
    ) {
        let weights = self.edge_weights(ctx, pose);
        let lens = edge_lengths(ctx.length, ctx.width);
        let (hl, hw) = (0.5 * ctx.length, 0.5 * ctx.width);
        let across = Normal::new(0.0, self.noise_sd(range(ctx, pose))).expect("finite positive sd");
        let along = Normal::new(0.0, self.along_noise).expect("finite non-negative sd");
        out.reserve(n);
        for _ in 0..n {
            let mut u: f64 = rng.random();
            let mut e = NUM_EDGES - 1;
            for (k, &p) in weights.iter().enumerate() {
                if u < p {
                    e = k;
                    break;
                }
                u -= p;
            }
            // Rounding can leave u >= 0 past the last positive weight: pick the last edge with weight.
            if weights[e] == 0.0 {
                e = (0..NUM_EDGES).rev().find(|&k| weights[k] > 0.0).unwrap_or(e);
            }
            let alpha = rng.random::<f64>() * lens[e] + along.sample(rng);
            let beta = across.sample(rng);
            let (bu, bv) = edge_point(e, alpha, beta, hl, hw);
            out.push(from_box_frame(pose, bu, bv));
            if let Some(edges) = edges.as_deref_mut() {
                edges.push(e);
            }
        }
    }

    /// Appends a Poisson number of points (mean [`PointGenerator::mean_count`] at the
    /// object's range) to `out`; returns how many.
    pub fn sample<R: Rng + ?Sized>(&self, ctx: &ObsContext, pose: Pose, rng: &mut R, out: &mut Vec<[f64; 2]>) -> usize {
        let mean = self.mean_count(range(ctx, pose));
        let n = if mean > 0.0 {
            let k: f64 = Poisson::new(mean).expect("positive finite mean").sample(rng);
            k as usize
        } else {
            0
        };
        self.sample_n(ctx, pose, n, rng, out, None);
        n
    }
}

/// Where random examples are drawn: the AV at the origin with a uniform heading;
/// the object at a uniform range in `range` (m) and uniform bearing, with a uniform
/// heading and uniform extents in `length` and `width` (m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneRanges {
    /// Range of the object from the AV (m).
    pub range: (f64, f64),
    /// Object length (m).
    pub length: (f64, f64),
    /// Object width (m).
    pub width: (f64, f64),
}

impl Default for SceneRanges {
    /// The synthetic scenes of SPEC §4: objects 5–50 m away, car-sized.
    fn default() -> Self {
        SceneRanges { range: (5.0, 50.0), length: (3.5, 5.5), width: (1.6, 2.2) }
    }
}

/// `n` labelled examples of the generator: random object states and sizes around
/// an AV (see [`SceneRanges`]) with their generated points (a Poisson number,
/// possibly none).
pub fn random_point_examples<R: Rng + ?Sized>(
    generator: &PointGenerator,
    ranges: &SceneRanges,
    n: usize,
    rng: &mut R,
) -> Vec<Example<[f64; 2]>> {
    let uniform = |rng: &mut R, (lo, hi): (f64, f64)| lo + (hi - lo) * rng.random::<f64>();
    (0..n)
        .map(|_| {
            let av = Pose { x: 0.0, y: 0.0, yaw: TAU * rng.random::<f64>() };
            let r = uniform(rng, ranges.range);
            let bearing = TAU * rng.random::<f64>();
            let pose = Pose { x: r * bearing.cos(), y: r * bearing.sin(), yaw: TAU * rng.random::<f64>() };
            let ctx = ObsContext::new(av, uniform(rng, ranges.length), uniform(rng, ranges.width));
            let mut items = Vec::new();
            generator.sample(&ctx, pose, rng, &mut items);
            Example { ctx, pose, items }
        })
        .collect()
}
