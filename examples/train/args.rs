//! The flags that several commands share: the files a training command reads and writes, and
//! the dtype of the weights it writes.

use clap::{Arg, Args, ValueEnum};
use drivesim::WeightDtype;
use std::path::PathBuf;

// --weights, --episodes, --heldout, --holdout, --no-mirror and --out: what `transition`,
// `vae-gan`, `fit` and `policy` start from, train and measure on, and write. No doc comments (clap would make this one the
// commands' about, and the flags' help differs between the commands): each command gives the
// flags their help with `data_help`.
#[derive(Args, Clone)]
pub struct Data {
    #[arg(long)]
    pub weights: PathBuf,
    #[arg(long)]
    pub episodes: PathBuf,
    #[arg(long)]
    pub heldout: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub holdout: usize,
    /// Train on the episodes only, not also on their mirror images (every frame flipped left
    /// to right, the steering negated: the drive on the mirrored track)
    #[arg(long)]
    pub no_mirror: bool,
    #[arg(long)]
    pub out: PathBuf,
}

/// For `#[command(mut_args = data_help(&[(flag, help), ...]))]` on a command that flattens
/// [`Data`]: gives each flag named its help, in place (`mut_arg` would move the flag to the end
/// of the usage line).
pub fn data_help(helps: &'static [(&'static str, &'static str)]) -> impl FnMut(Arg) -> Arg {
    move |arg| match helps.iter().find(|(id, _)| arg.get_id().as_str() == *id) {
        Some(&(_, help)) => arg.help(help),
        None => arg,
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub enum DtypeArg {
    F32,
    F16,
}

/// The weight dtype asked for, if any.
pub fn dtype(arg: Option<DtypeArg>) -> Option<WeightDtype> {
    arg.map(|d| match d {
        DtypeArg::F32 => WeightDtype::F32,
        DtypeArg::F16 => WeightDtype::F16,
    })
}
