//! Every diagnosis report committed under `results/` reads back under the
//! current schema and names the protocol it was made with.

use ssm::criticism::diagnose::{Protocol, Report, REPORT_FORMAT_VERSION};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn reports_below(dir: &Path, found: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            reports_below(&path, found);
        } else if path.file_name().is_some_and(|n| n == "report.json") {
            found.push(path);
        }
    }
}

/// Each committed report parses and its configuration is one named protocol's;
/// the studies whose protocol the guide names are read under that protocol.
#[test]
fn every_committed_report_reads_back_under_a_named_protocol() {
    let results = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results");
    let mut paths = Vec::new();
    reports_below(&results, &mut paths);
    assert!(paths.len() > 100, "only {} reports under {}", paths.len(), results.display());
    let mut by_study: BTreeMap<String, BTreeMap<&'static str, usize>> = BTreeMap::new();
    for path in &paths {
        let text = std::fs::read_to_string(path).unwrap();
        let report: Report = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        // Every committed report predates the format version: it reads back as version 0.
        assert_eq!(
            report.format_version,
            if text.contains("\"format_version\"") { REPORT_FORMAT_VERSION } else { 0 },
            "{}",
            path.display()
        );
        let protocol = Protocol::of(&report.config)
            .unwrap_or_else(|| panic!("{}: no protocol has the rules {:?}", path.display(), report.config));
        let study = path.strip_prefix(&results).unwrap().components().next().unwrap();
        let study = study.as_os_str().to_string_lossy().into_owned();
        *by_study.entry(study).or_default().entry(protocol.name).or_default() += 1;
    }
    for (study, protocols) in &by_study {
        println!("{study}: {protocols:?}");
    }
    let only = |study: &str| -> Vec<&'static str> { by_study[study].keys().copied().collect() };
    assert_eq!(only("power-study-set-aside"), ["v7"], "the default protocol's study");
    assert_eq!(only("power-study-fitted-screen"), ["v7-fitted-screen-full"]);
    assert_eq!(only("diagnose-student-t-default"), ["v7-fitted-screen"]);
    assert_eq!(only("diagnose-kitti-set-aside"), ["v7"]);
}
