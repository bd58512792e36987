//! Score-estimator cost on the vehicle model with point observations, f32, at the
//! sizes of SPEC §10: A (100 objects, T = 25) and B (100 objects, T = 50), both with
//! N = 1024 particles and lag L = 8, systematic resampling at every step.
//!
//! Workloads, each one call on the whole batch of 100 objects:
//! - **filter**: `run_filter` alone (lag 8, observer `()`), the floor under PF-SEFI;
//! - **pf-sefi** (L = 8), **pf**, **dpf-sgr** and **pfnet** (alpha 0.8): one
//!   `ScoreEstimator::estimate` call, i.e. one training step's gradient;
//! - **filter-t** and **pf-sefi-t**: the same on the tempered filter at the same
//!   `N` (`Tempering::for_observations` on point sets, as training and
//!   evaluation run it: the default path). They are timed interleaved with filter
//!   and PF-SEFI, so their ratios compare like with like on a loaded machine.
//!
//! **Precision per CPU-second**: a faster filter that is less precise is no
//! progress, so PF-SEFI on each filter is also run on 8 seeds (4 with `--quick`)
//! with one reduction block per object, and the table reports, as medians over
//! the objects, the sd of an object's `l_hat` and the spread of its score
//! (`sqrt` of the summed variances of its components) over the runs at the truth
//! that generated the data, with the merit `1 / (sd^2 x CPU s per run)`, and
//! the bias at the truth as `sefi score-at` measures it: per score component, the
//! `z` of the mean over objects of each object's mean score over the runs.
//!
//! The data and model are built as in `benches/filter.rs`: one synthetic scene
//! (seed 3) with the hand-crafted policy and an *unfitted* observation network (its
//! weights do not change the cost of a step; they do change how fast the particle
//! paths coalesce, hence PF-SEFI's count of distinct ancestors).
//!
//! **Time**: measured in this process on the default rayon pool (2 threads on this
//! machine); the median and the best of 5 repetitions after one warm-up run for
//! the cheap workloads (filter, PF-SEFI, whose repetitions alternate so their
//! ratio compares like with like), of 3 without a warm-up for the slow baselines,
//! so the whole bench takes five to ten minutes. Every repetition uses the same
//! seed, hence the same draws and the same work. The machine is shared:
//! before each timed workload the bench waits (up to 15 s) until other processes
//! use under a quarter of a core, and for every run it also records this
//! process's CPU time (`/proc/self/stat`) and the CPU time the rest of the machine
//! used meanwhile (`/proc/stat`), printed as "others' load" in cores, so a reader
//! can tell a slow figure from a contended one.
//!
//! **Peak memory**: each (workload, size) is run once in a fresh child process (the
//! bench re-executes itself, `std::env::current_exe()`, with `--child WORKLOAD SIZE
//! CHUNK`). The child builds the data and model, reads its resident set `VmRSS`
//! from `/proc/self/status`, resets the kernel's high-water mark by writing `5` to
//! `/proc/self/clear_refs` (so `VmHWM` restarts from the current RSS and excludes
//! the peak of data generation), runs one estimate, and reads `VmHWM`. The table
//! reports the RSS before, the peak, and peak minus before (what the estimate
//! itself added). If the reset is refused, the peak includes the setup and is
//! flagged. Children run one at a time, so they do not disturb each other or the
//! timings.
//!
//! The baselines process objects in chunks of `EstimatorConfig::chunk_objects`
//! (default 4; two chunks are in flight at once on two threads). DPF-SGR at B is
//! also measured with chunks of 1 and 8 to show the memory/time trade-off.
//!
//! Run: `cargo bench --bench estimators` (add `-- --quick` for one repetition of
//! everything, without warm-up, and no chunk sweep; `--size A|B` for one size;
//! `--no-memory` without the peak-memory children; `--no-wait` without waiting
//! for a quiet machine; `-- --default-path` for filter, PF-SEFI and
//! their tempered rows with the precision section only, without the baselines:
//! about three minutes with `--quick` on two cores; `--moves K`, `--ess F` and
//! `--lookback-only true|false` change those of the tempered rows' settings, to
//! weigh them). A single child run, e.g. for `perf record`:
//! `.../estimators --child pf-sefi A 4` (workloads: filter, pf-sefi, filter-t,
//! pf-sefi-t, pf, dpf-sgr, pfnet; sizes A, B). The child's line also carries the estimate's CPU time (both
//! threads, from `/proc/self/stat`), the figure to compare on a busy machine.

use std::process::Command;
use std::time::Instant;

use rand::rngs::StdRng;
use rand::SeedableRng;
use ssm::data::{Dataset, ObservationKind};
use ssm::estimators::{Estimator, EstimatorConfig, ScoreEstimator};
use ssm::filter::{run_filter, FilterPurpose, Sampling, Tempering};
use ssm::models::road_user::VehicleSsm;
use ssm::models::vehicle::policy::HandCraftedPolicy;
use ssm::models::ParticleModel;
use ssm::simulation::synthetic::{generate_dataset, SceneConfig, TrueModel};

/// Particles per object.
const PARTICLES: usize = 1024;
/// The fixed lag of PF-SEFI and of the filter-alone run.
const LAG: usize = 8;
/// PFNET's mixing weight (the paper's default).
const PFNET_ALPHA: f64 = 0.8;
/// Seed of the synthetic scene (as `benches/filter.rs`).
const DATA_SEED: u64 = 3;
/// Seed of the filter's random streams: every repetition sees the same draws.
const FILTER_SEED: u64 = 1;
/// Chunk sizes of the DPF-SGR sweep at B.
const SWEEP_CHUNKS: [usize; 3] = [1, 4, 8];
/// Seeds of the precision runs (`PRECISION_SEED + r`), apart from the timing seed.
const PRECISION_SEED: u64 = 1000;
/// Runs per filter in the precision section (and with `--quick`).
const PRECISION_RUNS: usize = 8;
const PRECISION_RUNS_QUICK: usize = 4;
/// Settings of the tempered rows that differ from the default's, to weigh a
/// setting: `--moves K`, `--ess F` and `--lookback-only BOOL` (the children
/// inherit them).
#[derive(Clone, Copy, Debug, Default)]
struct TemperingOverride {
    moves: Option<usize>,
    ess_fraction: Option<f64>,
    lookback_only: Option<bool>,
}

impl TemperingOverride {
    /// Reads the options from the command line.
    fn parse(args: &[String]) -> Self {
        let value = |flag: &str| args.iter().position(|a| a == flag).map(|p| args.get(p + 1).map(String::as_str));
        let parse = |flag: &str| value(flag).map(|v| v.unwrap_or_else(|| panic!("{flag} needs a value")));
        TemperingOverride {
            moves: parse("--moves").map(|v| v.parse().expect("--moves K (a count)")),
            ess_fraction: parse("--ess").map(|v| v.parse().expect("--ess F (a fraction)")),
            lookback_only: parse("--lookback-only").map(|v| v.parse().expect("--lookback-only true|false")),
        }
    }

    /// The options that give this override to a child.
    fn args(&self) -> Vec<String> {
        let mut a = Vec::new();
        if let Some(m) = self.moves {
            a.extend(["--moves".to_string(), m.to_string()]);
        }
        if let Some(f) = self.ess_fraction {
            a.extend(["--ess".to_string(), f.to_string()]);
        }
        if let Some(l) = self.lookback_only {
            a.extend(["--lookback-only".to_string(), l.to_string()]);
        }
        a
    }
}

/// `--no-wait`: time at once, without waiting for a quiet machine.
static NO_WAIT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
static TEMPERING_OVERRIDE: std::sync::OnceLock<TemperingOverride> = std::sync::OnceLock::new();
/// Tag of the line a child prints for its parent.
const CHILD_TAG: &str = "ESTIMATORS-CHILD";
const MIB: f64 = 1024.0 * 1024.0;
/// Other processes' load (cores) under which the machine counts as quiet.
const QUIET_LOAD: f64 = 0.25;
/// Longest wait for a quiet machine before each timed workload, seconds.
const QUIET_WAIT_MAX_S: f64 = 15.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Size {
    A,
    B,
}

impl Size {
    fn name(self) -> &'static str {
        match self {
            Size::A => "A",
            Size::B => "B",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        match s {
            "A" | "a" => Some(Size::A),
            "B" | "b" => Some(Size::B),
            _ => None,
        }
    }

    /// Transitions `T`.
    fn transitions(self) -> usize {
        match self {
            Size::A => 25,
            Size::B => 50,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Workload {
    Filter,
    PfSefi,
    /// The tempered filter alone (the default path's filter).
    TemperedFilter,
    /// PF-SEFI on the tempered filter (the default path's score).
    TemperedPfSefi,
    Pf,
    DpfSgr,
    Pfnet,
}

const WORKLOADS: [Workload; 7] = [
    Workload::Filter,
    Workload::PfSefi,
    Workload::TemperedFilter,
    Workload::TemperedPfSefi,
    Workload::Pf,
    Workload::DpfSgr,
    Workload::Pfnet,
];

impl Workload {
    fn name(self) -> &'static str {
        match self {
            Workload::Filter => "filter",
            Workload::PfSefi => "pf-sefi",
            Workload::TemperedFilter => "filter-t",
            Workload::TemperedPfSefi => "pf-sefi-t",
            Workload::Pf => "pf",
            Workload::DpfSgr => "dpf-sgr",
            Workload::Pfnet => "pfnet",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        WORKLOADS.iter().copied().find(|w| w.name() == s)
    }

    fn estimator(self) -> Option<Estimator> {
        match self {
            Workload::Filter | Workload::TemperedFilter => None,
            Workload::PfSefi | Workload::TemperedPfSefi => Some(Estimator::pf_sefi(LAG)),
            Workload::Pf => Some(Estimator::pf()),
            Workload::DpfSgr => Some(Estimator::dpf_sgr()),
            Workload::Pfnet => Some(Estimator::pfnet(PFNET_ALPHA)),
        }
    }

    /// Whether the workload runs the tempered filter (the default path).
    fn is_tempered(self) -> bool {
        matches!(self, Workload::TemperedFilter | Workload::TemperedPfSefi)
    }

    /// Whether the workload back-propagates through the whole filter (slow).
    fn is_baseline(self) -> bool {
        matches!(self, Workload::Pf | Workload::DpfSgr | Workload::Pfnet)
    }

    /// The SPEC §10 time target, seconds.
    fn time_target(self, size: Size) -> Option<f64> {
        match (self, size) {
            (Workload::Filter, Size::A) => Some(0.4),
            (Workload::PfSefi, Size::A) => Some(0.5),
            (Workload::PfSefi, Size::B) => Some(1.0),
            (Workload::DpfSgr, Size::A) => Some(1.8),
            _ => None,
        }
    }

    /// The SPEC §10 peak-memory target, bytes.
    fn memory_target(self, size: Size) -> Option<f64> {
        match (self, size) {
            (Workload::DpfSgr, Size::B) => Some(4.0 * 1024.0 * MIB),
            _ => None,
        }
    }
}

/// The synthetic scene of a size and the true model that drives it.
struct Problem {
    truth: TrueModel,
    data: Dataset,
}

impl Problem {
    fn new(size: Size) -> Self {
        let mut rng = StdRng::seed_from_u64(DATA_SEED);
        // The network's weights do not change the cost; an unfitted one avoids the fit.
        let truth = TrueModel::init(HandCraftedPolicy::truth(), &mut rng);
        let scene = SceneConfig::paper(size.transitions() + 1);
        let data = generate_dataset(&scene, &truth, &[0], &mut rng).expect("synthetic scene");
        Problem { truth, data }
    }

    fn model(&self) -> VehicleSsm<'_, HandCraftedPolicy, ssm::models::observation::PointObservationModel> {
        VehicleSsm::new(&self.data, &self.truth.policy, &self.truth.obs, &self.truth.params).expect("model")
    }
}

/// What one run of a workload reports besides its time.
#[derive(Clone, Copy, Debug, Default)]
struct Outcome {
    log_likelihood: f64,
    rows_evaluated: usize,
    particle_slots: usize,
    /// The filter-alone workloads: evaluations of all `N` particles' observation
    /// log-likelihoods, tempering stages, and the object-steps with an observation.
    likelihood_evaluations: usize,
    stages: usize,
    observed_steps: usize,
    /// Metropolis moves proposed and accepted (the tempered filter alone).
    moves_proposed: usize,
    moves_accepted: usize,
}

/// The estimator settings of `workload`: the bootstrap filter, or the tempered
/// filter the default path runs on point observations.
fn estimator_config(workload: Workload, chunk: usize) -> EstimatorConfig {
    let tempering = workload.is_tempered().then(|| {
        let default = Tempering::for_observations(ObservationKind::Points, FilterPurpose::Training);
        let o = TEMPERING_OVERRIDE.get().copied().unwrap_or_default();
        Tempering {
            moves: o.moves.unwrap_or(default.moves),
            ess_fraction: o.ess_fraction.unwrap_or(default.ess_fraction),
            lookback_only: o.lookback_only.unwrap_or(default.lookback_only),
            ..default
        }
    });
    EstimatorConfig { chunk_objects: chunk, ..EstimatorConfig::new(Sampling::new(PARTICLES, tempering)) }
}

/// Runs `workload` once on the whole batch of objects.
fn run_once<M: ssm::models::DifferentiableModel>(model: &M, workload: Workload, chunk: usize) -> Outcome {
    let config = estimator_config(workload, chunk);
    match workload.estimator() {
        None => {
            let filter = config.filter(FILTER_SEED, LAG, None);
            let run = run_filter(model, &filter, |_| ());
            let observed_steps = (0..model.num_objects())
                .map(|o| (0..model.num_steps()).filter(|&t| model.observation_count(o, t) > 0).count())
                .sum();
            Outcome {
                log_likelihood: run.log_likelihood(),
                rows_evaluated: 0,
                particle_slots: PARTICLES * model.num_steps() * model.num_objects(),
                likelihood_evaluations: run.objects.iter().map(|o| o.likelihood_evaluations).sum(),
                stages: run.objects.iter().map(|o| o.tempering_stages).sum(),
                observed_steps,
                moves_proposed: run.objects.iter().map(|o| o.moves_proposed).sum(),
                moves_accepted: run.objects.iter().map(|o| o.moves_accepted).sum(),
            }
        }
        Some(estimator) => {
            let estimate = estimator.estimate(model, &config, FILTER_SEED);
            assert!(estimate.is_finite(), "{}: non-finite estimate", workload.name());
            Outcome {
                log_likelihood: estimate.log_likelihood,
                rows_evaluated: estimate.rows_evaluated,
                particle_slots: estimate.particle_slots,
                ..Outcome::default()
            }
        }
    }
}

/// CPU-time counters, in clock ticks.
#[derive(Clone, Copy, Debug)]
struct CpuTicks {
    /// Busy time of the whole machine (every process, every core).
    machine_busy: u64,
    /// Time of this process (user + system, all threads).
    this_process: u64,
}

/// Reads the machine's busy ticks (`/proc/stat`) and this process's (`/proc/self/stat`).
fn cpu_ticks() -> Option<CpuTicks> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let cpu: Vec<u64> = stat.lines().next()?.split_whitespace().skip(1).map(|v| v.parse().unwrap_or(0)).collect();
    // user nice system idle iowait irq softirq steal (guest time is inside user).
    let machine_busy = cpu.iter().take(8).enumerate().filter(|&(i, _)| i != 3 && i != 4).map(|(_, v)| v).sum();
    let own = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name `(...)`: state is field 3, utime 14, stime 15.
    let rest: Vec<&str> = own[own.rfind(')')? + 1..].split_whitespace().collect();
    let this_process = rest.get(11)?.parse::<u64>().ok()? + rest.get(12)?.parse::<u64>().ok()?;
    Some(CpuTicks { machine_busy, this_process })
}

/// Clock ticks per second of the `/proc` counters.
fn ticks_per_second() -> f64 {
    Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8_lossy(&o.stdout).trim().parse().ok())
        .unwrap_or(100.0)
}

/// Waits (at most [`QUIET_WAIT_MAX_S`]) until other processes use less than
/// [`QUIET_LOAD`] cores over a one-second window; returns the seconds waited and
/// whether the machine became quiet.
fn wait_for_quiet(tick_rate: f64) -> (f64, bool) {
    let start = Instant::now();
    if NO_WAIT.get().copied().unwrap_or(false) {
        return (0.0, false);
    }
    while start.elapsed().as_secs_f64() < QUIET_WAIT_MAX_S {
        let (Some(a), t) = (cpu_ticks(), Instant::now()) else { return (0.0, false) };
        std::thread::sleep(std::time::Duration::from_secs(1));
        let Some(b) = cpu_ticks() else { return (0.0, false) };
        let others = (b.machine_busy - a.machine_busy).saturating_sub(b.this_process - a.this_process);
        if others as f64 / tick_rate / t.elapsed().as_secs_f64() < QUIET_LOAD {
            return (start.elapsed().as_secs_f64(), true);
        }
    }
    (start.elapsed().as_secs_f64(), false)
}

/// Times of repeated runs.
#[derive(Clone, Debug)]
struct Timing {
    /// Wall time per run.
    seconds: Vec<f64>,
    /// This process's CPU time per run (both threads).
    cpu_seconds: Vec<f64>,
    /// CPU time used by other processes on the machine during each run.
    others_seconds: Vec<f64>,
}

fn median(values: &[f64]) -> f64 {
    let mut s = values.to_vec();
    s.sort_by(f64::total_cmp);
    let m = s.len() / 2;
    if s.len() % 2 == 1 {
        s[m]
    } else {
        0.5 * (s[m - 1] + s[m])
    }
}

impl Timing {
    fn median(&self) -> f64 {
        median(&self.seconds)
    }

    fn best(&self) -> f64 {
        self.seconds.iter().copied().fold(f64::INFINITY, f64::min)
    }

    fn cpu_median(&self) -> f64 {
        median(&self.cpu_seconds)
    }

    /// Mean number of cores other processes kept busy while this ran.
    fn others_load(&self) -> f64 {
        self.others_seconds.iter().sum::<f64>() / self.seconds.iter().sum::<f64>()
    }
}

/// Times `workloads` after waiting for a quiet machine, their repetitions
/// interleaved (`a b a b ...`) so that a change in other processes' load falls on
/// all of them alike.
fn time_workloads<M: ssm::models::DifferentiableModel>(
    model: &M,
    workloads: &[Workload],
    chunk: usize,
    warm_up: bool,
    reps: usize,
    tick_rate: f64,
) -> Vec<(Timing, Outcome)> {
    let (waited, quiet) = wait_for_quiet(tick_rate);
    if waited > 1.5 || (!quiet && waited > 0.0) {
        println!(
            "  (waited {waited:.0} s for other processes to go below {QUIET_LOAD} cores{})",
            if quiet { "" } else { "; they did not" }
        );
    }
    if warm_up {
        for &w in workloads {
            run_once(model, w, chunk);
        }
    }
    let mut out: Vec<(Timing, Outcome)> = workloads
        .iter()
        .map(|_| {
            (Timing { seconds: Vec::new(), cpu_seconds: Vec::new(), others_seconds: Vec::new() }, Outcome::default())
        })
        .collect();
    for _ in 0..reps {
        for (&w, (timing, outcome)) in workloads.iter().zip(out.iter_mut()) {
            let before = cpu_ticks();
            let t = Instant::now();
            *outcome = run_once(model, w, chunk);
            timing.seconds.push(t.elapsed().as_secs_f64());
            if let (Some(a), Some(b)) = (before, cpu_ticks()) {
                let own = b.this_process - a.this_process;
                let others = (b.machine_busy - a.machine_busy).saturating_sub(own);
                timing.cpu_seconds.push(own as f64 / tick_rate);
                timing.others_seconds.push(others as f64 / tick_rate);
            }
        }
    }
    out
}

/// A field of `/proc/self/status` in bytes (`VmRSS`, `VmHWM`).
fn proc_status_bytes(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field) && l[field.len()..].starts_with(':'))?;
    let kib: u64 = line[field.len() + 1..].trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib * 1024)
}

/// Resets `VmHWM` to the current RSS (Linux >= 4.0).
fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// The child: one run of one workload, then a line for the parent.
fn child(args: &[String]) {
    let usage = "usage: estimators --child WORKLOAD SIZE CHUNK";
    let workload = Workload::parse(args.first().expect(usage)).expect("unknown workload");
    let size = Size::parse(args.get(1).expect(usage)).expect("unknown size (A or B)");
    let chunk: usize = args.get(2).map_or(EstimatorConfig::default().chunk_objects, |c| c.parse().expect(usage));
    let problem = Problem::new(size);
    let model = problem.model();
    let before = proc_status_bytes("VmRSS").expect("VmRSS");
    let reset = reset_peak_rss();
    let cpu_before = cpu_ticks();
    let t = Instant::now();
    let outcome = run_once(&model, workload, chunk);
    let seconds = t.elapsed().as_secs_f64();
    let cpu_seconds = match (cpu_before, cpu_ticks()) {
        (Some(a), Some(b)) => (b.this_process - a.this_process) as f64 / ticks_per_second(),
        _ => f64::NAN,
    };
    let peak = proc_status_bytes("VmHWM").expect("VmHWM");
    println!(
        "{CHILD_TAG} {before} {peak} {} {seconds} {} {} {} {cpu_seconds}",
        reset as u8, outcome.rows_evaluated, outcome.particle_slots, outcome.log_likelihood
    );
}

/// Peak memory of one child run.
#[derive(Clone, Copy, Debug)]
struct Memory {
    before: f64,
    peak: f64,
    reset: bool,
    seconds: f64,
    /// CPU time of the estimate in the child (both threads).
    cpu_seconds: f64,
}

impl Memory {
    fn added(&self) -> f64 {
        self.peak - self.before
    }
}

fn measure_memory(workload: Workload, size: Size, chunk: usize) -> Option<Memory> {
    let exe = std::env::current_exe().ok()?;
    let mut command = Command::new(exe);
    if let Some(o) = TEMPERING_OVERRIDE.get() {
        command.args(o.args());
    }
    let out = command.args(["--child", workload.name(), size.name(), &chunk.to_string()]).output().ok()?;
    if !out.status.success() {
        eprintln!(
            "child {} {} {chunk} failed: {}\n{}",
            workload.name(),
            size.name(),
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        return None;
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().find(|l| l.starts_with(CHILD_TAG))?;
    let f: Vec<&str> = line.split_whitespace().collect();
    Some(Memory {
        before: f.get(1)?.parse().ok()?,
        peak: f.get(2)?.parse().ok()?,
        reset: *f.get(3)? == "1",
        seconds: f.get(4)?.parse().ok()?,
        cpu_seconds: f.get(8)?.parse().ok()?,
    })
}

/// One row of the final table.
struct Row {
    size: Size,
    workload: Workload,
    chunk: Option<usize>,
    timing: Timing,
    outcome: Outcome,
    memory: Option<Memory>,
}

fn mib(bytes: f64) -> String {
    format!("{:.0}", bytes / MIB)
}

fn verdict(value: f64, target: Option<f64>) -> &'static str {
    match target {
        None => "",
        Some(t) if value <= t => "yes",
        Some(_) => "NO",
    }
}

fn reps_for(workload: Workload, quick: bool) -> usize {
    match (quick, workload.is_baseline()) {
        (true, _) => 1,
        (false, false) => 5,
        (false, true) => 3,
    }
}

/// PF-SEFI's precision at the truth on one filter over repeated runs.
struct Spread {
    /// Runs (seeds).
    runs: usize,
    /// Median over objects of the sd of an object's `l_hat` over the runs.
    loglik_sd: f64,
    /// Median over objects of the spread of an object's score over the runs:
    /// `sqrt(trace Cov)`, the root of the summed variances of its components.
    score_sd: f64,
    /// Median CPU seconds of one run on the whole batch (both threads).
    cpu_seconds: f64,
    /// Bias at the truth, as `sefi score-at` measures it: per score component,
    /// `z = mean / se` of the objects' mean scores over the runs (the objects are
    /// independent draws, each with mean score zero at the truth); the largest
    /// `|z|`, and how many components have `|z| > 3` of how many.
    max_abs_z: f64,
    over_3: usize,
    components: usize,
}

impl Spread {
    /// Precision per CPU-second: `1 / (sd^2 x CPU s per run)`, the number of
    /// runs' worth of variance reduction a CPU-second buys (a filter twice as
    /// precise at four times the cost scores the same).
    fn merit(sd: f64, cpu: f64) -> f64 {
        1.0 / (sd * sd * cpu)
    }
}

/// The sample sd of `values`.
fn sample_sd(values: &[f64]) -> f64 {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt()
}

/// Runs PF-SEFI (`workload`: on the bootstrap or the tempered filter) `runs`
/// times with seeds `PRECISION_SEED + r`, one reduction block per object, and
/// measures the spread of each object's `l_hat` and score over the runs. The
/// model is the one that generated the data, so this is the spread at the truth.
fn precision<M: ssm::models::DifferentiableModel>(
    model: &M,
    workload: Workload,
    runs: usize,
    tick_rate: f64,
) -> Spread {
    let config = estimator_config(workload, 1);
    let estimator = workload.estimator().expect("a score workload");
    let objects = model.num_objects();
    // [object][run]
    let mut loglik = vec![Vec::with_capacity(runs); objects];
    let mut score: Vec<Vec<Vec<f64>>> = vec![Vec::with_capacity(runs); objects];
    let mut cpu = Vec::with_capacity(runs);
    for r in 0..runs {
        let before = cpu_ticks();
        let partial = estimator.partial(model, &config, PRECISION_SEED + r as u64);
        if let (Some(a), Some(b)) = (before, cpu_ticks()) {
            cpu.push((b.this_process - a.this_process) as f64 / tick_rate);
        }
        assert_eq!(partial.blocks.len(), objects, "one block per object");
        for (o, block) in partial.blocks.into_iter().enumerate() {
            loglik[o].push(block.log_likelihood);
            score[o].push(block.gradient);
        }
    }
    let loglik_sds: Vec<f64> = loglik.iter().map(|l| sample_sd(l)).collect();
    let score_sds: Vec<f64> = score
        .iter()
        .map(|runs_of_object| {
            let dim = runs_of_object[0].len();
            (0..dim)
                .map(|k| sample_sd(&runs_of_object.iter().map(|g| g[k]).collect::<Vec<_>>()).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    let dim = score.first().map_or(0, |o| o[0].len());
    let z: Vec<f64> = (0..dim)
        .map(|k| {
            let means: Vec<f64> = score.iter().map(|o| o.iter().map(|g| g[k]).sum::<f64>() / o.len() as f64).collect();
            let mean = means.iter().sum::<f64>() / objects as f64;
            let se = sample_sd(&means) / (objects as f64).sqrt();
            if se > 0.0 {
                mean / se
            } else {
                0.0
            }
        })
        .collect();
    Spread {
        runs,
        loglik_sd: median(&loglik_sds),
        score_sd: median(&score_sds),
        cpu_seconds: median(&cpu),
        max_abs_z: z.iter().fold(0.0, |m, v| m.max(v.abs())),
        over_3: z.iter().filter(|v| v.abs() > 3.0).count(),
        components: dim,
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    TEMPERING_OVERRIDE.set(TemperingOverride::parse(&args)).expect("set once");
    if let Some(pos) = args.iter().position(|a| a == "--child") {
        child(&args[pos + 1..]);
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    let skip_baselines = args.iter().any(|a| a == "--default-path");
    let skip_memory = args.iter().any(|a| a == "--no-memory");
    let no_wait = args.iter().any(|a| a == "--no-wait");
    let sizes: Vec<Size> = match args.iter().position(|a| a == "--size") {
        Some(p) => vec![args.get(p + 1).and_then(|s| Size::parse(s)).expect("--size A|B")],
        None => vec![Size::A, Size::B],
    };
    NO_WAIT.set(no_wait).expect("set once");
    let precision_runs = if quick { PRECISION_RUNS_QUICK } else { PRECISION_RUNS };
    let default_chunk = EstimatorConfig::default().chunk_objects;
    let threads = rayon::current_num_threads();
    let tick_rate = ticks_per_second();
    let started = Instant::now();
    println!(
        "score-estimator benchmark: N = {PARTICLES}, L = {LAG}, pfnet alpha = {PFNET_ALPHA}, f32, systematic \
         resampling, {threads} rayon threads, baselines in chunks of {default_chunk} objects"
    );

    println!("tempered rows: {:?}", estimator_config(Workload::TemperedFilter, default_chunk).sampling.tempering);
    let mut rows: Vec<Row> = Vec::new();
    let mut spreads: Vec<(Size, Workload, Spread)> = Vec::new();
    for &size in &sizes {
        let problem = Problem::new(size);
        let model = problem.model();
        let points: usize = problem.data.points().map(|p| p.len()).unwrap_or(0);
        println!(
            "\nsize {}: {} objects, T = {} ({} steps), {:.1} points per object-step",
            size.name(),
            model.num_objects(),
            size.transitions(),
            model.num_steps(),
            points as f64 / (model.num_objects() * model.num_steps()) as f64
        );
        // Filter and PF-SEFI interleaved (their ratio is a target), then each baseline.
        // The tempered rows join them: the default path's cost against the paper's filter.
        let all: [&[Workload]; 4] = [
            &[Workload::Filter, Workload::PfSefi, Workload::TemperedFilter, Workload::TemperedPfSefi],
            &[Workload::Pf],
            &[Workload::DpfSgr],
            &[Workload::Pfnet],
        ];
        let groups = if skip_baselines { &all[..1] } else { &all[..] };
        for &group in groups {
            let reps = reps_for(group[0], quick);
            let warm_up = !group[0].is_baseline() && !quick;
            let timed = time_workloads(&model, group, default_chunk, warm_up, reps, tick_rate);
            for (&workload, (timing, outcome)) in group.iter().zip(timed) {
                let memory = if skip_memory { None } else { measure_memory(workload, size, default_chunk) };
                println!(
                    "  {:<8} median {:7.3} s  best {:7.3} s  cpu {:7.3} s  others {:.2} cores  ({} reps{})  \
                     peak +{} MiB  l_hat {:.1}{}",
                    workload.name(),
                    timing.median(),
                    timing.best(),
                    timing.cpu_median(),
                    timing.others_load(),
                    reps,
                    if warm_up { " after a warm-up" } else { "" },
                    memory.map_or("?".into(), |m| mib(m.added())),
                    outcome.log_likelihood,
                    if workload.is_tempered() && outcome.observed_steps > 0 {
                        format!(
                            "  {:.2} likelihood evaluations and {:.2} stages per observed object-step, \
                             {:.1}% of moves accepted",
                            outcome.likelihood_evaluations as f64 / outcome.observed_steps as f64,
                            outcome.stages as f64 / outcome.observed_steps as f64,
                            100.0 * outcome.moves_accepted as f64 / outcome.moves_proposed.max(1) as f64
                        )
                    } else {
                        String::new()
                    }
                );
                let chunk = workload.is_baseline().then_some(default_chunk);
                rows.push(Row { size, workload, chunk, timing, outcome, memory });
            }
        }
        for workload in [Workload::PfSefi, Workload::TemperedPfSefi] {
            wait_for_quiet(tick_rate);
            let spread = precision(&model, workload, precision_runs, tick_rate);
            println!(
                "  {:<9} precision over {} runs: median sd of l_hat {:.3}, of the score {:.3}, cpu {:.2} s per run; \
                 score at the truth: max |z| {:.2}, {} of {} components with |z| > 3",
                workload.name(),
                spread.runs,
                spread.loglik_sd,
                spread.score_sd,
                spread.cpu_seconds,
                spread.max_abs_z,
                spread.over_3,
                spread.components
            );
            spreads.push((size, workload, spread));
        }
    }

    // DPF-SGR at B: the memory/time trade-off of the chunk size.
    let mut sweep: Vec<Row> = Vec::new();
    if !quick && !skip_baselines {
        let problem = Problem::new(Size::B);
        let model = problem.model();
        println!("\nDPF-SGR at B, chunk sweep");
        for chunk in SWEEP_CHUNKS {
            if chunk == default_chunk {
                if let Some(r) = rows.iter().find(|r| r.size == Size::B && r.workload == Workload::DpfSgr) {
                    sweep.push(Row { chunk: Some(chunk), timing: r.timing.clone(), ..*r });
                    continue;
                }
            }
            let (timing, outcome) = time_workloads(&model, &[Workload::DpfSgr], chunk, false, 1, tick_rate).remove(0);
            let memory = measure_memory(Workload::DpfSgr, Size::B, chunk);
            println!(
                "  chunk {chunk}: {:7.3} s (cpu {:.3} s, others {:.2} cores), peak +{} MiB",
                timing.median(),
                timing.cpu_median(),
                timing.others_load(),
                memory.map_or("?".into(), |m| mib(m.added()))
            );
            sweep.push(Row { size: Size::B, workload: Workload::DpfSgr, chunk: Some(chunk), timing, outcome, memory });
        }
    }

    println!("\n## Time per training step (one estimate on all 100 objects) and peak memory\n");
    println!(
        "| size | workload | chunk | median s | best s | reps | cpu s | others' load | time target | met | \
         RSS before MiB | peak MiB | peak - before MiB | memory target | met | child run s | child cpu s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let target = r.workload.time_target(r.size);
        let mem_target = r.workload.memory_target(r.size);
        let (before, peak, added, mem_ok, child_s, child_cpu) = match r.memory {
            Some(m) => (
                mib(m.before),
                format!("{}{}", mib(m.peak), if m.reset { "" } else { " (incl. setup)" }),
                mib(m.added()),
                verdict(m.peak, mem_target).to_string(),
                format!("{:.2}", m.seconds),
                format!("{:.2}", m.cpu_seconds),
            ),
            None => ("?".into(), "?".into(), "?".into(), "?".into(), "?".into(), "?".into()),
        };
        println!(
            "| {} | {} | {} | {:.3} | {:.3} | {} | {:.3} | {:.2} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            r.size.name(),
            r.workload.name(),
            r.chunk.map_or("-".into(), |c| c.to_string()),
            r.timing.median(),
            r.timing.best(),
            r.timing.seconds.len(),
            r.timing.cpu_median(),
            r.timing.others_load(),
            target.map_or(String::new(), |t| format!("<= {t} s")),
            verdict(r.timing.median(), target),
            before,
            peak,
            added,
            mem_target.map_or(String::new(), |t| format!("<= {} GiB", t / (1024.0 * MIB))),
            mem_ok,
            child_s,
            child_cpu
        );
    }

    println!("\n## PF-SEFI against the filter alone (medians of interleaved runs)\n");
    println!(
        "| size | filter s | pf-sefi s | surrogate s (difference) | ratio | target | met | filter cpu s | pf-sefi cpu s | \
         cpu ratio |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for size in [Size::A, Size::B] {
        let find = |w: Workload| rows.iter().find(|r| r.size == size && r.workload == w);
        if let (Some(f), Some(s)) = (find(Workload::Filter), find(Workload::PfSefi)) {
            let ratio = s.timing.median() / f.timing.median();
            println!(
                "| {} | {:.3} | {:.3} | {:.3} | {:.2} | <= 1.5 | {} | {:.3} | {:.3} | {:.2} |",
                size.name(),
                f.timing.median(),
                s.timing.median(),
                s.timing.median() - f.timing.median(),
                ratio,
                verdict(ratio, Some(1.5)),
                f.timing.cpu_median(),
                s.timing.cpu_median(),
                s.timing.cpu_median() / f.timing.cpu_median()
            );
        }
    }

    println!("\n## The default path: the tempered filter against the bootstrap filter (same N, interleaved runs)\n");
    println!(
        "| size | filter s | filter-t s | filter-t / filter | pf-sefi s | pf-sefi-t s | pf-sefi-t / pf-sefi | target | \
         met | cpu ratio pf-sefi-t / pf-sefi | evaluations per observed object-step (filter-t) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for size in [Size::A, Size::B] {
        let find = |w: Workload| rows.iter().find(|r| r.size == size && r.workload == w);
        if let (Some(f), Some(s), Some(ft), Some(st)) = (
            find(Workload::Filter),
            find(Workload::PfSefi),
            find(Workload::TemperedFilter),
            find(Workload::TemperedPfSefi),
        ) {
            let ratio = st.timing.median() / s.timing.median();
            println!(
                "| {} | {:.3} | {:.3} | {:.2} | {:.3} | {:.3} | {:.2} | <= 3 | {} | {:.2} | {:.2} |",
                size.name(),
                f.timing.median(),
                ft.timing.median(),
                ft.timing.median() / f.timing.median(),
                s.timing.median(),
                st.timing.median(),
                ratio,
                verdict(ratio, Some(3.0)),
                st.timing.cpu_median() / s.timing.cpu_median(),
                ft.outcome.likelihood_evaluations as f64 / ft.outcome.observed_steps.max(1) as f64
            );
        }
    }

    println!("\n## Precision at the truth per CPU-second (PF-SEFI, one block per object, seeds {PRECISION_SEED}..)\n");
    println!(
        "sd: median over objects of the sd over runs of an object's l_hat, and of its score (sqrt of the summed \
         variances of the components); merit = 1 / (sd^2 x CPU s per run on all objects), higher is better.\n"
    );
    println!(
        "| size | workload | runs | cpu s per run | sd l_hat | sd score | merit l_hat | merit score | \
         merit l_hat / bootstrap's | merit score / bootstrap's | max abs z of the mean score | components with abs z > 3 |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (size, workload, s) in &spreads {
        let base = spreads.iter().find(|(z, w, _)| z == size && *w == Workload::PfSefi).map(|(_, _, b)| b);
        let (ml, ms) = (Spread::merit(s.loglik_sd, s.cpu_seconds), Spread::merit(s.score_sd, s.cpu_seconds));
        let (rl, rs) = base.map_or((f64::NAN, f64::NAN), |b| {
            (ml / Spread::merit(b.loglik_sd, b.cpu_seconds), ms / Spread::merit(b.score_sd, b.cpu_seconds))
        });
        println!(
            "| {} | {} | {} | {:.3} | {:.4} | {:.4} | {:.3e} | {:.3e} | {:.2} | {:.2} | {:.2} | {} of {} |",
            size.name(),
            workload.name(),
            s.runs,
            s.cpu_seconds,
            s.loglik_sd,
            s.score_sd,
            ml,
            ms,
            rl,
            rs,
            s.max_abs_z,
            s.over_3,
            s.components
        );
    }

    println!("\n## Baselines against PF-SEFI: ratio of median wall times (of median CPU times)\n");
    println!("| size | pf / pf-sefi | dpf-sgr / pf-sefi | pfnet / pf-sefi |");
    println!("|---|---|---|---|");
    for size in [Size::A, Size::B] {
        let timing = |w: Workload| rows.iter().find(|r| r.size == size && r.workload == w).map(|r| &r.timing);
        if let Some(s) = timing(Workload::PfSefi) {
            let ratio = |w| {
                timing(w).map_or("?".into(), |t| {
                    format!("{:.1} ({:.1})", t.median() / s.median(), t.cpu_median() / s.cpu_median())
                })
            };
            println!(
                "| {} | {} | {} | {} |",
                size.name(),
                ratio(Workload::Pf),
                ratio(Workload::DpfSgr),
                ratio(Workload::Pfnet)
            );
        }
    }

    println!("\n## PF-SEFI distinct ancestors (rows evaluated on the tape)\n");
    println!("| size | rows_evaluated | particle_slots = N x (T+1) x objects | share |");
    println!("|---|---|---|---|");
    for r in rows.iter().filter(|r| r.workload == Workload::PfSefi) {
        println!(
            "| {} | {} | {} | {:.2}% |",
            r.size.name(),
            r.outcome.rows_evaluated,
            r.outcome.particle_slots,
            100.0 * r.outcome.rows_evaluated as f64 / r.outcome.particle_slots as f64
        );
    }
    println!("(SPEC §10 expects about 7% at A)");

    if !sweep.is_empty() {
        println!("\n## DPF-SGR at B: objects per tape chunk (time: one run each, chunk {default_chunk} from above)\n");
        println!(
            "| chunk | time s | cpu s | others' load | RSS before MiB | peak MiB | peak - before MiB | under 4 GiB |"
        );
        println!("|---|---|---|---|---|---|---|---|");
        for r in &sweep {
            let (before, peak, added, ok) = match r.memory {
                Some(m) => (
                    mib(m.before),
                    mib(m.peak),
                    mib(m.added()),
                    verdict(m.peak, Workload::DpfSgr.memory_target(Size::B)),
                ),
                None => ("?".into(), "?".into(), "?".into(), "?"),
            };
            println!(
                "| {} | {:.3} | {:.3} | {:.2} | {} | {} | {} | {} |",
                r.chunk.unwrap_or(default_chunk),
                r.timing.median(),
                r.timing.cpu_median(),
                r.timing.others_load(),
                before,
                peak,
                added,
                ok
            );
        }
    }
    println!("\nbench wall time {:.0} s", started.elapsed().as_secs_f64());
}
