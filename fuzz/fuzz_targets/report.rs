//! A diagnosis's `report.json` read back ([`Report`] from JSON), and what
//! `sefi stability` and `sefi power-study` read off it: the decision under the
//! current rules, with and without rule (d), why an expected cause was missed,
//! each candidate's gain by part and the bars.
#![no_main]
use libfuzzer_sys::fuzz_target;
use ssm::criticism::diagnose::Report;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(report) = serde_json::from_str::<Report>(text) else { return };
    for check_rule in [true, false] {
        let verdicts = report.verdicts(check_rule);
        let _ = report.outcome(&verdicts);
        let _ = report.decided(check_rule);
    }
    for c in &report.candidates {
        let _ = report.gains_by_part(c);
        let _ = report.decided_for(&c.cause);
        let _ = report.why_not(&c.cause);
    }
    for expected in ["none", "unexplained", "heavy_tailed_accel"] {
        let _ = report.decided_for(expected);
        let _ = report.why_not(expected);
    }
    let _ = report.shown_candidate(&report.cause);
    let _ = report.eval_part();
    let _ = report.unmeasured_bar();
    let _ = report.gain_bar();
    let _ = report.reference_checks();
});
