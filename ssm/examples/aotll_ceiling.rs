//! How high a supervised box network scores on KITTI's val AOTLL, fitted on
//! train (experiment C's SUPERVISED row, over several seeds) and fitted on the
//! val labels themselves. The supervised fit maximises AOTLL (SPEC §4), so the
//! second — in-sample, and overfitting by as much as the network can — is about
//! the most a box network of this architecture, self-supervised or not, can
//! score on val; the gap between the two is what separates the splits. Both fits
//! observe the heading flips in the labels (`heading_flip` at their share, as
//! experiment C's `--extension heading_flip`), at the paper scale's settings
//! (6000 Adam steps of 256 detections at lr 0.01, detection offsets zero), from
//! the initial weights experiment C draws for the same seed.
//!
//! ```text
//! sefi import-kitti --out K
//! cargo run --release -p ssm --example aotll_ceiling -- K 0,1,2
//! ```
//! prints, per seed, each fit's AOTLL on train and val (nats per detection).

use std::path::Path;

use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::{Dataset, ObservationKind};
use ssm::evaluation::metrics::models_aotll;
use ssm::models::observation::boxes::DetectionOffsets;
use ssm::models::observation::FitConfig;
use ssm::models::params::{AnyPolicy, Models};
use ssm::models::vehicle::neural::NeuralPolicy;
use ssm::training::supervised::fit_observation_with_flips;

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let root = Path::new(args.get(1).map(String::as_str).unwrap_or("out/kitti"));
    let seeds: Vec<u64> = match args.get(2) {
        Some(s) => {
            s.split(',').map(|x| x.trim().parse().map_err(|e| format!("seed `{x}`: {e}"))).collect::<Result<_, _>>()?
        }
        None => vec![0],
    };
    let read =
        |split: &str| Dataset::read(root.join(split)).map_err(|e| format!("{}: {e}", root.join(split).display()));
    let (train, val) = (read("train")?, read("val")?);
    println!("| fitted on | seed | train AOTLL | val AOTLL | flips in the fitted labels |");
    println!("|---|---|---|---|---|");
    for &seed in &seeds {
        for (name, fitted_on) in [("train", &train), ("val", &val)] {
            let policy = AnyPolicy::Neural(NeuralPolicy::new(&mut StdRng::seed_from_u64(seed)));
            let mut models = Models::initial_with_offsets(
                ObservationKind::Boxes,
                policy,
                seed.wrapping_add(1),
                DetectionOffsets::Zero,
            );
            let fit = FitConfig { steps: 6000, batch: 256, lr: 0.01, clip: None, seed };
            fit_observation_with_flips(&mut models, fitted_on, &fit)?;
            let flips = models
                .extension
                .as_ref()
                .map(|e| e.extension.natural(&e.raw))
                .transpose()
                .map_err(|e| e.to_string())?;
            let flips = flips.and_then(|v| v.first().map(|p| p.1)).unwrap_or(0.0);
            println!(
                "| {name} | {seed} | {:.4} | {:.4} | {:.2}% |",
                models_aotll(&train, &models).mean.unwrap_or(f64::NAN),
                models_aotll(&val, &models).mean.unwrap_or(f64::NAN),
                100.0 * flips
            );
        }
    }
    Ok(())
}
