//! Data-parallel training over MPI (cargo feature `mpi`): the job's communicator
//! as an [`ssm::util::reduce::Collective`], the rule that only the first process
//! writes, and a failing process ending the whole job.
//!
//! Launch: `mpiexec -n 4 sefi train ...` (or `reproduce`, `experiment-c`,
//! `diagnose`) with a binary built with `--features mpi`. Every process reads
//! only its blocks of the training objects ([`ssm::training::objective::owned_objects`],
//! [`ssm::data::Dataset::read_shard`]) and steps in lock-step; the
//! exact reduction of [`ssm::util::reduce`] gives every process, for any number of
//! processes, the parameters a single process computes, bit for bit. A panic on
//! any process aborts the communicator (no process waits forever in a
//! collective), as does an error returned by a command.
//!
//! Without the feature, or with `SEFI_NO_MPI=1`, there is one process and
//! nothing here talks to MPI.

use std::sync::Arc;

use ssm::util::reduce::{Collective, SingleProcess};

/// The job this process belongs to.
pub struct Cluster {
    comm: Arc<dyn Collective>,
    #[cfg(feature = "mpi")]
    _universe: Option<mpi::environment::Universe>,
}

impl Cluster {
    /// One process, no MPI.
    pub fn single() -> Self {
        Cluster {
            comm: Arc::new(SingleProcess),
            #[cfg(feature = "mpi")]
            _universe: None,
        }
    }

    /// Joins the MPI job this process was started in (a job of one when started
    /// without `mpiexec`), unless `SEFI_NO_MPI` is set or the feature is off.
    /// With more than one process, installs the panic hook that aborts the job.
    pub fn join() -> Self {
        #[cfg(feature = "mpi")]
        if std::env::var_os("SEFI_NO_MPI").is_none() {
            return mpi_backend::join();
        }
        Cluster::single()
    }

    /// The communicator, for the objectives.
    pub fn collective(&self) -> Arc<dyn Collective> {
        self.comm.clone()
    }

    /// This process's index.
    pub fn rank(&self) -> usize {
        self.comm.rank()
    }

    /// Number of processes.
    pub fn size(&self) -> usize {
        self.comm.size()
    }

    /// Whether this process writes files and shows progress.
    pub fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Waits until every process of the job has reached this call (a one-value
    /// reduction); returns at once in a job of one.
    pub fn barrier(&self) {
        if self.size() > 1 {
            self.comm.max_f64(&mut [0.0]);
        }
    }

    /// Every process waits here until the first has done work only it does
    /// (preparing the data, say) and learns whether it succeeded (`first_ok`, as
    /// the first process passes it; the others' argument is ignored). When it
    /// failed, the other processes block until the first reports its error and
    /// ends the job ([`Cluster::fail`]), so that its message is the one shown.
    pub fn wait_for_first(&self, first_ok: bool) {
        if self.size() == 1 {
            return;
        }
        let mut failed = [if self.is_root() && !first_ok { 1.0 } else { 0.0 }];
        self.comm.max_f64(&mut failed);
        if failed[0] > 0.0 && !self.is_root() {
            // Never completes: the first process aborts the job.
            self.barrier();
        }
    }

    /// On a job of many processes, prints how many there are and how many bytes
    /// this process has sent in the reductions (the line a command ends with,
    /// which also shows that its work was shared); nothing on a job of one.
    pub fn print_traffic(&self) {
        if self.size() > 1 {
            println!(
                "{} processes; {} bytes sent by this process in the reductions",
                self.size(),
                self.comm.bytes_sent()
            );
        }
    }

    /// Ends the whole job after a command failed on this process (the others may
    /// be waiting in a collective); returns only in a job of one.
    pub fn fail(&self, code: i32) {
        #[cfg(feature = "mpi")]
        if self.size() > 1 {
            mpi_backend::abort(code);
        }
        let _ = code;
    }

    /// Fails at step `step` on the process named by `SEFI_FAIL_AT_STEP` and
    /// `SEFI_FAIL_RANK` (default rank 0): a panic with a clear message, or with
    /// `SEFI_FAIL_HOW=abort` the process killed by `SIGABRT` (no panic hook, no
    /// unwinding). The failures the tests inject to check that a job ends promptly
    /// and resumes bit for bit.
    pub fn inject_failure(&self, step: usize) {
        let at: Option<usize> = std::env::var("SEFI_FAIL_AT_STEP").ok().and_then(|v| v.parse().ok());
        let rank: usize = std::env::var("SEFI_FAIL_RANK").ok().and_then(|v| v.parse().ok()).unwrap_or(0);
        if at == Some(step) && rank == self.rank() {
            if std::env::var("SEFI_FAIL_HOW").is_ok_and(|h| h == "abort") {
                eprintln!("injected abort at step {step} on process {rank} (SEFI_FAIL_AT_STEP)");
                std::process::abort();
            }
            panic!("injected failure at step {step} on process {rank} (SEFI_FAIL_AT_STEP)");
        }
    }
}

#[cfg(feature = "mpi")]
mod mpi_backend {
    //! The rsmpi communicator behind [`Collective`].

    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;

    use mpi::collective::SystemOperation;
    use mpi::environment::Threading;
    use mpi::topology::SimpleCommunicator;
    use mpi::traits::*;
    use ssm::util::reduce::Collective;

    use super::Cluster;

    /// `MPI_COMM_WORLD`; every call comes from the main thread (MPI's
    /// "funneled" level: rayon's workers never call MPI).
    struct World {
        comm: SimpleCommunicator,
        sent: AtomicU64,
    }

    // SAFETY: the communicator is only used from the thread that initialised MPI
    // (the objectives' reductions run on the training loop's thread), as the
    // funneled threading level requires; the bounds only let it sit in an `Arc`.
    unsafe impl Send for World {}
    unsafe impl Sync for World {}

    impl Collective for World {
        fn rank(&self) -> usize {
            self.comm.rank() as usize
        }
        fn size(&self) -> usize {
            self.comm.size() as usize
        }
        fn max_f64(&self, values: &mut [f64]) {
            let local = values.to_vec();
            self.comm.all_reduce_into(&local[..], values, SystemOperation::max());
            self.sent.fetch_add(8 * values.len() as u64, Ordering::Relaxed);
        }
        fn sum_i64(&self, values: &mut [i64]) {
            let local = values.to_vec();
            self.comm.all_reduce_into(&local[..], values, SystemOperation::sum());
            self.sent.fetch_add(8 * values.len() as u64, Ordering::Relaxed);
        }
        fn bytes_sent(&self) -> u64 {
            self.sent.load(Ordering::Relaxed)
        }
    }

    pub(super) fn join() -> Cluster {
        let Some((universe, _)) = mpi::initialize_with_threading(Threading::Funneled) else {
            // Already initialised in this process: a programmer error.
            panic!("MPI was initialised twice");
        };
        let world = World { comm: universe.world(), sent: AtomicU64::new(0) };
        if world.size() > 1 {
            let default = std::panic::take_hook();
            std::panic::set_hook(Box::new(move |info| {
                default(info);
                abort(70);
            }));
        }
        Cluster { comm: Arc::new(world), _universe: Some(universe) }
    }

    /// Aborts every process of the job with `code`.
    pub(super) fn abort(code: i32) -> ! {
        eprintln!("aborting the MPI job (exit code {code})");
        SimpleCommunicator::world().abort(code)
    }
}
