//! `sefi stability` on committed diagnoses of KITTI: every held-out set's
//! outcome as the current rules decide it, each candidate's gains by KITTI
//! sequence as the report's own split gives them, and clear errors that write
//! nothing.

use std::path::{Path, PathBuf};

use ssm::criticism::diagnose::Report;

use crate::common::{failed, ok, s, sefi, temp};

/// Committed diagnoses of two KITTI held-out sets (the shared val sequences,
/// and half a of the train sequences).
fn committed() -> [PathBuf; 2] {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../results/diagnose-kitti-set-aside");
    [root.join("train-to-val"), root.join("b-to-a")]
}

fn report(dir: &Path) -> Report {
    serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap()
}

#[test]
fn stability_sets_each_held_out_sets_finding_side_by_side() {
    let out = temp("stability", "kitti");
    let [val, half] = committed();
    let stdout = ok(&sefi(&["stability", s(&val), s(&half), "--labels", "val,half a", "--out", s(&out)]));
    let reports = [report(&val), report(&half)];
    let outcomes: Vec<String> = reports.iter().map(|r| r.decided(true).0).collect();
    for o in &outcomes {
        assert!(stdout.contains(&format!("`{o}` on")), "{o}: {stdout}");
    }
    let sets: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stability.json")).unwrap()).unwrap();
    let sets = sets.as_array().unwrap();
    assert_eq!(sets.len(), 2);
    for ((set, r), outcome) in sets.iter().zip(&reports).zip(&outcomes) {
        assert_eq!(set["outcome"].as_str().unwrap(), outcome);
        assert_eq!(set["part"].as_str().unwrap(), "kitti_sequence");
        let recorded = (r.cause != *outcome).then_some(r.cause.as_str());
        assert_eq!(set["recorded"].as_str(), recorded);
        let shown = r.shown_candidate(outcome).map(|c| c.cause.as_str());
        assert_eq!(set["shown"].as_str(), shown, "the extension split by part is the outcome's");
        let candidates = set["candidates"].as_array().unwrap();
        assert_eq!(candidates.len(), r.candidates.len());
        for ((c, rc), verdict) in candidates.iter().zip(&r.candidates).zip(r.verdicts(true)) {
            assert_eq!(c["cause"].as_str().unwrap(), rc.cause);
            assert_eq!(c["fails"].as_str().map(str::to_owned), verdict.map(|rule| rule.to_string()), "{}", rc.cause);
            let parts = r.gains_by_part(rc).expect("a per-object record");
            let units: usize = parts.iter().map(|g| g.units).sum();
            assert_eq!(units, r.eval_units, "{}: the parts hold every evaluated unit", rc.cause);
            let listed = c["parts"].as_array().unwrap();
            assert_eq!(listed.len(), parts.len());
            for (l, g) in listed.iter().zip(&parts) {
                assert_eq!(l["group"].as_i64().unwrap(), g.group);
                // JSON keeps the gain to its last bit or so.
                assert!((l["gain"].as_f64().unwrap() - g.gain).abs() <= 1e-12 * g.gain.abs().max(1.0), "{l} {g:?}");
            }
        }
    }
    let md = std::fs::read_to_string(out.join("stability.md")).unwrap();
    assert!(md.contains("| val | 664 |") && md.contains("KITTI sequence 19"), "{md}");
    let svg = std::fs::read_to_string(out.join("stability.svg")).unwrap();
    assert!(svg.contains(&format!("val: {}", outcomes[0])) && svg.contains("seq. 9"), "the forest plot's rows");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn stability_refuses_what_it_cannot_read_and_writes_nothing() {
    let out = temp("stability", "refused");
    let [val, _] = committed();
    let empty = temp("stability", "no-report");
    std::fs::create_dir_all(&empty).unwrap();
    let err = failed(&sefi(&["stability", s(&val), s(&empty), "--out", s(&out)]));
    assert!(err.contains(&format!("{}", empty.join("report.json").display())), "{err}");
    std::fs::write(empty.join("report.json"), "{\"cause\": 3}").unwrap();
    let err = failed(&sefi(&["stability", s(&empty), "--out", s(&out)]));
    assert!(err.contains("report.json") && err.contains("not a diagnosis report"), "{err}");
    let err = failed(&sefi(&["stability", s(&val), "--labels", "a,b", "--out", s(&out)]));
    assert!(err.contains("--labels") && err.contains("one label per directory"), "{err}");
    assert!(!out.exists(), "nothing written");
    std::fs::remove_dir_all(&empty).unwrap();
}
