//! The diagnosis as a library call: generate point data with a hidden sensor
//! lag (the observations show the pose 0.15 s ago), hand the data alone to
//! [`diagnose`], and print what it finds: the checks the fitted base model
//! fails, the extensions it fitted with their held-out gains, and the cause.
//!
//! `cargo run --release --example diagnose`
//!
//! The full size is the quick scale of `sefi diagnose --quick` with shorter fits
//! (the scale of `sefi demo`'s criticism stage): 48 objects, a few minutes.
use std::sync::Arc;

use ssm::criticism::diagnose::{diagnose, DiagnoseConfig, Report};
use ssm::criticism::hidden::{generate_hidden, HiddenConfig, HiddenEffect};
use ssm::data::ObservationKind;
use ssm::util::reduce::{Collective, SingleProcess};

/// Diagnoses generated data with a hidden lag at `scenes` scenes of `steps`
/// steps, fitting the base for `base_steps` and each candidate for half as many
/// (training runs go under a temporary directory); prints and returns the report.
fn diagnose_hidden_lag(scenes: usize, steps: usize, base_steps: usize, particles: usize) -> Report {
    let seed = 1;
    let effect = HiddenEffect::at_strength("latency", 1.0).unwrap();
    let hidden = HiddenConfig { scenes, steps, ..HiddenConfig::quick(ObservationKind::Points, effect, seed) };
    let data = generate_hidden(&hidden).unwrap();
    let config = DiagnoseConfig {
        base_steps,
        candidate_steps: base_steps * 2 / 5,
        particles,
        eval_particles: 4 * particles,
        seed,
        ..DiagnoseConfig::quick()
    };
    let runs = tempfile::tempdir().unwrap();
    let comm: Arc<dyn Collective> = Arc::new(SingleProcess);
    let report = diagnose(&data, &config, runs.path(), &comm, &mut |_| {}).unwrap();

    println!(
        "{} objects: {} fit the models, {} check them, {} evaluate",
        data.objects().len(),
        report.train_objects,
        report.check_objects,
        report.eval_objects
    );
    println!("checks the base fails (uncorrected p < {}):", config.plausible_p);
    for c in report.checks.iter().filter(|c| c.before.p < config.plausible_p) {
        println!("  {:<28} z {:+6.2}  suggests {}", c.name, c.before.z, c.suggests.as_deref().unwrap_or("-"));
    }
    println!("fitted extensions, gain on the evaluation objects (nats per point):");
    for c in &report.candidates {
        println!("  {:<28} {:+.4} ± {:.4}  p adj. {:.4}", c.cause, c.gain, c.gain_se, c.p_adjusted);
    }
    println!("cause: {}  {}", report.cause, report.finding);
    println!("{:.0} s", report.seconds);
    report
}

fn main() {
    diagnose_hidden_lag(8, 16, 150, 256);
}

#[cfg(test)]
mod tests {
    /// At a tiny scale (its fits too short to name anything) the call runs end
    /// to end on generated data, and the report it returns decides as it says:
    /// deciding again from its own candidates and checks names the same outcome.
    #[test]
    fn the_diagnosis_runs_and_its_report_is_consistent() {
        let report = super::diagnose_hidden_lag(3, 6, 5, 32);
        assert_eq!(report.train_objects + report.check_objects + report.eval_objects, 18);
        assert_eq!(report.decided(true).0, report.cause);
        assert!(!report.checks.is_empty());
    }
}
