//! What `reproduce` and `experiment-c` share: their command-line scale, methods
//! and filters ([`TableArgs`]) and their result tables, the SPEC §5 metrics of
//! each method as median \[IQR\] over runs, in Markdown and as CSV rows.

use std::fmt::Write as _;

use ssm::evaluation::metrics::{summarise_runs, Metrics};
use ssm::stats::Summary;

use crate::args::FilterArgs;

/// The methods a Table 1 run trains by default, in the table's order: the
/// estimators on the bootstrap filter (the paper's setting), then PF-SEFI on the
/// tempered filter.
pub const DEFAULT_METHODS: &str = "pf-sefi,dpf-sgr,pfnet,pf,pf-sefi-tempered";

/// The settings of a Table 1 run (`reproduce`, `experiment-c`): its scale, the
/// methods it trains and the filters.
#[derive(clap::Args, Clone, Debug)]
pub struct TableArgs {
    /// Tiny sizes: the whole pipeline in a few minutes (for tests).
    #[arg(long, conflicts_with = "paper")]
    pub quick: bool,
    /// The paper's settings for this experiment (particles, lag, 100 epochs; README).
    #[arg(long)]
    pub paper: bool,
    /// Methods to train (comma-separated): the estimators on the bootstrap filter
    /// (the paper's setting) and `pf-sefi-tempered`, PF-SEFI on the tempered filter.
    #[arg(long, value_delimiter = ',', default_value = DEFAULT_METHODS)]
    pub methods: Vec<String>,
    /// The evaluation's filter (the same for every method and TRUE) and the
    /// tempered filter's settings.
    #[command(flatten)]
    pub filter: FilterArgs,
    /// Override the scale's training particles per object.
    #[arg(long)]
    pub particles: Option<usize>,
    /// Override the scale's training epochs.
    #[arg(long)]
    pub epochs: Option<usize>,
}

/// The metrics of the tables, in order, with their Markdown headers.
pub const METRIC_COLUMNS: [(&str, &str); 7] = [
    ("mll", "MLL"),
    ("aotll", "AOTLL"),
    ("aptll", "APTLL"),
    ("ade_smoothed", "ADE sm (m)"),
    ("aye_smoothed", "AYE sm (rad)"),
    ("ade_filtered", "ADE filt (m)"),
    ("aye_filtered", "AYE filt (rad)"),
];

/// The header of the CSV rows [`metric_cells`] writes.
pub const CSV_HEADER: &str = "method,metric,median,q1,q3,n\n";

/// `median [q1, q3]`, or the value alone for one run, or `-`.
pub fn summary_cell(s: Option<&Summary>) -> String {
    match s {
        Some(s) if s.n > 1 => format!("{:.3} [{:.3}, {:.3}]", s.median, s.q1, s.q3),
        Some(s) => format!("{:.3}", s.median),
        None => "-".into(),
    }
}

/// The Markdown header row and separator: `method`, the metric columns, then `extra`.
pub fn header(extra: &[&str]) -> String {
    let mut md = String::from("| method |");
    for (_, h) in METRIC_COLUMNS {
        let _ = write!(md, " {h} |");
    }
    for h in extra {
        let _ = write!(md, " {h} |");
    }
    md.push_str("\n|---|");
    for _ in 0..METRIC_COLUMNS.len() + extra.len() {
        md.push_str("---|");
    }
    md.push('\n');
    md
}

/// One CSV row of a summary.
pub fn csv_row(csv: &mut String, method: &str, metric: &str, s: &Summary) {
    let _ = writeln!(csv, "{method},{metric},{},{},{},{}", s.median, s.q1, s.q3, s.n);
}

/// Starts `method`'s Markdown row with its metric cells (median \[IQR\] over `runs`)
/// and adds their CSV rows; returns every metric's summary for further columns.
/// The caller appends its extra cells and the line end.
pub fn metric_cells(
    method: &str,
    runs: &[Metrics],
    md: &mut String,
    csv: &mut String,
) -> Vec<(&'static str, Option<Summary>)> {
    let summary = summarise_runs(runs);
    let _ = write!(md, "| {method} |");
    for (name, _) in METRIC_COLUMNS {
        let s = summary.iter().find(|(n, _)| *n == name).and_then(|(_, s)| s.as_ref());
        let _ = write!(md, " {} |", summary_cell(s));
        if let Some(s) = s {
            csv_row(csv, method, name, s);
        }
    }
    summary
}
