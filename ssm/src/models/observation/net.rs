//! The plain (no-tape) forward pass of an observation network over a batch of
//! particles: heading trig and features, then the network through
//! [`crate::models::plain_mlp`].

use autodiff::nn::{Mlp, ParamStore};
use autodiff::Float;

use super::features::{features_with_trig, NUM_FEATURES};
use super::{fit_len, ObsContext, PosesRef, Scratch};
use crate::models::plain_mlp::forward_feature_major;

/// Runs an observation network for `poses` on the plain (no-tape) path: heading
/// trig, AV-relative features and the raw outputs, all into `scratch`.
#[allow(clippy::needless_range_loop)] // index loops over resliced arrays vectorise
pub(crate) fn forward_plain<F: Float>(
    mlp: &Mlp,
    params: &ParamStore<F>,
    ctx: &ObsContext,
    poses: PosesRef<'_, F>,
    scratch: &mut Scratch<F>,
) {
    let n = poses.len();
    fit_len(&mut scratch.cos, n);
    fit_len(&mut scratch.sin, n);
    // An index loop over equal-length slices vectorises (a zip of zips did not).
    let (cos, sin, yaw) = (&mut scratch.cos[..n], &mut scratch.sin[..n], &poses.yaw[..n]);
    for i in 0..n {
        cos[i] = yaw[i].cos();
        sin[i] = yaw[i].sin();
    }
    fit_len(&mut scratch.feats, NUM_FEATURES * n);
    features_with_trig(ctx, poses, &scratch.cos, &scratch.sin, &mut scratch.feats);
    forward_feature_major(mlp, params.values(), n, &scratch.feats, &mut scratch.hidden, &mut scratch.outputs);
}
