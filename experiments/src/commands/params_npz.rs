//! `sefi params`: parameter files to and from NumPy's `.npz` (one float64 array
//! per parameter, keyed by name), so they can be read and written outside Rust.

use std::path::PathBuf;

use autodiff::nn::ParamStore;
use clap::Subcommand;

/// Conversions of parameter files.
#[derive(clap::Args)]
pub struct ParamsArgs {
    #[command(subcommand)]
    action: ParamsAction,
}

#[derive(Subcommand)]
enum ParamsAction {
    /// Write a parameter file as `.npz` (`numpy.load(OUT)` gives one array per parameter).
    Export {
        /// The parameter file (as written by `sefi train` or `generate`).
        params: PathBuf,
        /// The `.npz` to write.
        out: PathBuf,
    },
    /// Read an `.npz` (as `numpy.savez` writes it, uncompressed) into a parameter file.
    Import {
        /// The `.npz` archive.
        npz: PathBuf,
        /// The parameter file to write.
        out: PathBuf,
        /// A parameter file whose names and shapes the archive must have.
        #[arg(long)]
        like: Option<PathBuf>,
    },
}

/// Runs `sefi params export|import`.
pub fn run(args: &ParamsArgs) -> Result<(), String> {
    match &args.action {
        ParamsAction::Export { params, out } => {
            let store = ParamStore::<f64>::load(params).map_err(|e| e.to_string())?;
            ssm::util::npz::write_params(&store, out).map_err(|e| e.to_string())?;
            println!("{}: {} parameters ({} values)", out.display(), store.len(), store.num_scalars());
        }
        ParamsAction::Import { npz, out, like } => {
            let like = like.as_ref().map(|p| ParamStore::<f64>::load(p)).transpose().map_err(|e| e.to_string())?;
            let store = ssm::util::npz::read_params(npz, like.as_ref()).map_err(|e| e.to_string())?;
            store.save(out).map_err(|e| e.to_string())?;
            println!("{}: {} parameters ({} values)", out.display(), store.len(), store.num_scalars());
        }
    }
    Ok(())
}
