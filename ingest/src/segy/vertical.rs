//! The vertical axis: time or depth, its unit, its first sample and its step.
//!
//! SEG-Y has no binary field that says whether traces are sampled in time or in depth:
//! depth cubes store their depth step in the sample-interval field that time cubes fill
//! with microseconds. What a file says about its domain it says in words, in the textual
//! headers ("PSDM", "DEPTH MIGRATED", "TWO-WAY TIME", …). The domain is decided, in this
//! order, by the `--vertical` option, by the domain of the `--vertical-unit` option (ms and
//! s are time, m and ft depth), by the words of the textual and extended textual headers,
//! and otherwise assumed to be time (recorded as assumed, with how to override it). An
//! option that contradicts the headers wins, with a warning. A depth cube is never
//! labelled milliseconds.
//!
//! Words are weighed: specific phrases ("PSDM", "DEPTH MIGRATED", "TIME MIGRATED",
//! "TWO-WAY TIME", …) are strong evidence; the bare time words "TWT", "MSEC" and
//! "MILLISECOND(S)" are weak, since depth cubes' headers mention them too. Strong evidence
//! for both domains is an error that asks for `--vertical`; strong evidence for one beats
//! weak evidence for the other, with a warning.
//!
//! The sample-interval field holds the step × 1000 in the vertical unit: microseconds for
//! millisecond time, and by the same convention millimetres (or thousandths of a foot) for
//! depth, as segyio, OpendTect and most interpretation software read it. Rev 2's extended
//! sample interval (bytes 3273-3280, an IEEE double in the same unit) wins over the 16-bit
//! field where it is set; `--z-step` wins over both.

use super::header::{with_40_lines, Layout};
use anyhow::{bail, Result};
use std::path::Path;
pub use strata_common::store::VerticalDomain;

/// Unit of the vertical axis.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum VerticalUnit {
    /// Milliseconds (time).
    Ms,
    /// Seconds (time).
    S,
    /// Metres (depth).
    M,
    /// Feet (depth).
    Ft,
}

impl VerticalUnit {
    /// The name stored in a page store's units and accepted on the command line.
    pub fn name(self) -> &'static str {
        match self {
            VerticalUnit::Ms => "ms",
            VerticalUnit::S => "s",
            VerticalUnit::M => "m",
            VerticalUnit::Ft => "ft",
        }
    }

    /// The domain the unit measures.
    pub fn domain(self) -> VerticalDomain {
        match self {
            VerticalUnit::Ms | VerticalUnit::S => VerticalDomain::Time,
            VerticalUnit::M | VerticalUnit::Ft => VerticalDomain::Depth,
        }
    }

    /// How many of this unit one thousandth of the field's base unit is: the sample
    /// interval field holds µs for time and thousandths of a metre or foot for depth.
    fn per_field_step(self) -> f64 {
        match self {
            VerticalUnit::Ms | VerticalUnit::M | VerticalUnit::Ft => 1e-3,
            VerticalUnit::S => 1e-6,
        }
    }

    /// How many of this unit one unit of the delay field is (ms for time; the depth unit
    /// itself for depth).
    fn per_delay_unit(self) -> f64 {
        match self {
            VerticalUnit::S => 1e-3,
            _ => 1.0,
        }
    }
}

/// What was decided about the vertical axis, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct VerticalAxis {
    /// Time or depth.
    pub domain: VerticalDomain,
    /// The unit of [`VerticalAxis::start`] and [`VerticalAxis::step`].
    pub unit: VerticalUnit,
    /// z of sample 0.
    pub start: f64,
    /// z step between samples (> 0).
    pub step: f64,
    /// Where the domain came from: `"--vertical"`, `"--vertical-unit …"`, a quoted phrase
    /// of a textual header with its line, or [`ASSUMED_TIME`].
    pub domain_from: String,
    /// Where the unit came from.
    pub unit_from: String,
}

/// [`VerticalAxis::domain_from`] when nothing said time or depth.
pub const ASSUMED_TIME: &str =
    "assumed: the textual headers do not say time or depth (pass --vertical depth, or --vertical-unit m or ft, \
     for a depth cube)";

/// Smallest and largest sample step accepted (in the vertical unit): a step that vanishes
/// against the lateral bins would make the grid-to-world transform singular.
const MIN_STEP: f64 = 1e-6;
const MAX_STEP: f64 = 1e9;

/// Phrases (upper case, words separated by single blanks) that say a file is in depth.
const DEPTH_PHRASES: &[&str] = &[
    "DEPTH DOMAIN",
    "DOMAIN DEPTH",
    "DEPTH MIGRATED",
    "DEPTH MIGRATION",
    "PSDM",
    "PRESTACK DEPTH",
    "PRE STACK DEPTH",
    "DEPTH CUBE",
    "DEPTH VOLUME",
    "DEPTH DATA",
    "DEPTH SECTION",
    "DEPTH CONVERTED",
    "Z DEPTH",
    "TVDSS",
];

/// Phrases that say a file is in time.
const TIME_PHRASES: &[&str] = &[
    "TIME DOMAIN",
    "DOMAIN TIME",
    "TWO WAY TIME",
    "TWO WAY TRAVEL TIME",
    "TIME MIGRATED",
    "TIME MIGRATION",
    "PSTM",
    "PRESTACK TIME",
    "PRE STACK TIME",
    "TIME CUBE",
    "TIME VOLUME",
    "TIME DATA",
    "TIME SECTION",
    "Z TIME",
];

/// Words that suggest time, but also turn up in depth files' headers.
const WEAK_TIME_WORDS: &[&str] = &["TWT", "MSEC", "MILLISECOND", "MILLISECONDS"];

/// Words that name a depth unit.
const FEET_WORDS: &[&str] = &["FT", "FEET", "FOOT"];
const METRE_WORDS: &[&str] = &["METER", "METERS", "METRE", "METRES"];

/// One phrase found in a textual header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Evidence {
    /// 1-based line of the textual headers (the main header's 40 lines, then the extended
    /// headers' lines).
    pub(crate) line: usize,
    pub(crate) phrase: &'static str,
}

impl Evidence {
    fn describe(&self) -> String {
        format!("textual header line {}: '{}'", self.line, self.phrase)
    }
}

/// Upper case, every run of characters other than letters and digits one blank, with a
/// blank at both ends, so phrases match on word boundaries.
fn words(line: &str) -> String {
    let mut out = String::from(" ");
    for c in line.chars() {
        if c.is_ascii_alphanumeric() {
            out.push(c.to_ascii_uppercase());
        } else if !out.ends_with(' ') {
            out.push(' ');
        }
    }
    if !out.ends_with(' ') {
        out.push(' ');
    }
    out
}

/// The first phrase of `phrases` on each line of `text` that has one.
pub(crate) fn find(text: &str, phrases: &[&'static str]) -> Vec<Evidence> {
    text.lines()
        .enumerate()
        .filter_map(|(n, line)| {
            let w = words(line);
            phrases
                .iter()
                .find(|p| w.contains(&format!(" {p} ")))
                .map(|&phrase| Evidence {
                    line: n + 1,
                    phrase,
                })
        })
        .collect()
}

/// Decides the vertical axis of a file.
///
/// `delay` is trace 1's delay recording time (byte 109) and `delay_scalar` its scalar
/// (bytes 215-216, rev 1 and 2 only; 0 for none).
pub(crate) fn decide(
    path: &Path,
    layout: &Layout,
    delay: i16,
    delay_scalar: i16,
    vertical: Option<VerticalDomain>,
    vertical_unit: Option<VerticalUnit>,
    z_step: Option<f64>,
    warnings: &mut Vec<String>,
) -> Result<VerticalAxis> {
    let p = path.display();
    // Main header lines 1-40, then the extended headers' lines.
    let mut text = with_40_lines(&layout.text_header);
    text.push_str(&layout.extended_text);
    let depth = find(&text, DEPTH_PHRASES);
    let time = find(&text, TIME_PHRASES);
    let weak_time = find(&text, WEAK_TIME_WORDS);

    if let (Some(d), Some(u)) = (vertical, vertical_unit) {
        if u.domain() != d {
            bail!(
                "{p}: --vertical-unit {} is a {} unit, but --vertical says {}",
                u.name(),
                u.domain().name(),
                d.name()
            );
        }
    }
    let option = match (vertical, vertical_unit) {
        (Some(d), _) => Some((d, "--vertical".to_string())),
        (None, Some(u)) => Some((u.domain(), format!("--vertical-unit {}", u.name()))),
        (None, None) => None,
    };
    // What the headers say, if anything.
    let said: Option<(VerticalDomain, String)> = match (
        depth.first(),
        time.first(),
        weak_time.first(),
    ) {
        (Some(d), Some(t), _) => {
            if option.is_none() {
                bail!(
                    "{p}: the textual headers say both depth ({}) and time ({}); pass --vertical time or \
                     --vertical depth",
                    d.describe(),
                    t.describe()
                );
            }
            None
        }
        (Some(d), None, Some(w)) => {
            if option.is_none() {
                warnings.push(format!(
                    "the textual headers say depth ({}) and mention time ({}); read as depth (pass --vertical \
                     time if it is time)",
                    d.describe(),
                    w.describe()
                ));
            }
            Some((VerticalDomain::Depth, d.describe()))
        }
        (Some(d), None, None) => Some((VerticalDomain::Depth, d.describe())),
        (None, Some(t), _) => Some((VerticalDomain::Time, t.describe())),
        (None, None, Some(w)) => Some((VerticalDomain::Time, w.describe())),
        (None, None, None) => None,
    };
    let (domain, domain_from) = match (option, said) {
        (Some((d, from)), Some((h, why))) => {
            if d != h {
                warnings.push(format!(
                    "{from} makes the traces {}, though the textual headers say {} ({why})",
                    d.name(),
                    h.name()
                ));
            }
            (d, from)
        }
        (Some(o), None) => o,
        (None, Some(h)) => h,
        // Most files say nothing and are time; not a warning, but `domain_from` says so.
        (None, None) => (VerticalDomain::Time, ASSUMED_TIME.to_string()),
    };

    let (unit, unit_from) = match (vertical_unit, domain) {
        (Some(u), _) => (u, "--vertical-unit".to_string()),
        (None, VerticalDomain::Time) => (VerticalUnit::Ms, "time is in ms".to_string()),
        (None, VerticalDomain::Depth) => {
            // Unit words on the lines that say depth or name it, then the binary header's
            // measurement system, then metres.
            let lines: String = text
                .lines()
                .enumerate()
                .filter(|(n, l)| {
                    depth.iter().any(|e| e.line == n + 1) || words(l).contains(" DEPTH ")
                })
                .map(|(_, l)| l)
                .collect::<Vec<_>>()
                .join("\n");
            let feet = find(&lines, FEET_WORDS);
            let metres = find(&lines, METRE_WORDS);
            match (
                feet.is_empty(),
                metres.is_empty(),
                layout.measurement_system,
            ) {
                (false, true, _) => (VerticalUnit::Ft, "feet on a line about depth".to_string()),
                (true, false, _) => (VerticalUnit::M, "metres on a line about depth".to_string()),
                (_, _, 1) => (
                    VerticalUnit::M,
                    "binary header byte 3255 (measurement system 1, metres)".into(),
                ),
                (_, _, 2) => (
                    VerticalUnit::Ft,
                    "binary header byte 3255 (measurement system 2, feet)".into(),
                ),
                _ => {
                    warnings.push(
                        "depth unit not stated (binary header byte 3255 is neither 1, metres, nor 2, feet); read as \
                         metres (pass --vertical-unit ft for feet)"
                            .into(),
                    );
                    (VerticalUnit::M, "assumed".to_string())
                }
            }
        }
    };

    let step = match z_step {
        Some(s) => {
            if !(MIN_STEP..=MAX_STEP).contains(&s) {
                bail!(
                    "{p}: --z-step {s}: expected a sample step in {} from {MIN_STEP:e} to {MAX_STEP:e}",
                    unit.name()
                );
            }
            s
        }
        None => match layout.extended_interval {
            // The 16-bit field's range (1..=65535 thousandths) and then some; anything
            // else is garbage, not a finer step.
            Some(x) if (1e-3..=1e9).contains(&x) => x * unit.per_field_step(),
            _ if layout.sample_interval_raw == 0 => {
                warnings.push(format!(
                    "sample interval is 0 in the binary header (byte 3217) and trace 1's header (byte 117); assuming \
                     1000, i.e. {} {} per sample (pass --z-step to set it)",
                    1000.0 * unit.per_field_step(),
                    unit.name()
                ));
                1000.0 * unit.per_field_step()
            }
            Some(x) => {
                warnings.push(format!(
                    "binary header bytes 3273-3280 (rev 2 extended sample interval) hold {x:e}, which is no sample \
                     interval; using bytes 3217-3218 ({})",
                    layout.sample_interval_raw
                ));
                layout.sample_interval_raw as f64 * unit.per_field_step()
            }
            None => layout.sample_interval_raw as f64 * unit.per_field_step(),
        },
    };
    let scale = match delay_scalar {
        0 | 1 => 1.0,
        s if s > 0 => s as f64,
        s => 1.0 / -(s as f64),
    };
    let start = delay as f64 * scale * unit.per_delay_unit();
    if domain == VerticalDomain::Depth && z_step.is_none() {
        let span = step * layout.samples_per_trace as f64;
        let ft = if unit == VerticalUnit::Ft {
            3.28084
        } else {
            1.0
        };
        if !(10.0 * ft..=100_000.0 * ft).contains(&span) {
            warnings.push(format!(
                "{} samples of {step} {} span {span} {}, which is not a plausible depth range; the sample \
                 interval field holds the depth step x 1000 by convention (pass --z-step if the file stores it \
                 otherwise)",
                layout.samples_per_trace,
                unit.name(),
                unit.name()
            ));
        }
    }
    Ok(VerticalAxis {
        domain,
        unit,
        start,
        step,
        domain_from,
        unit_from,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phrases_match_whole_words_on_their_line() {
        let text = "C 1 CLIENT: X\nC 2 KIRCHHOFF PRE-STACK DEPTH MIGRATION\nC 3 WATER DEPTH 120 M";
        let d = find(text, DEPTH_PHRASES);
        assert_eq!(
            d,
            vec![Evidence {
                line: 2,
                phrase: "DEPTH MIGRATION"
            }]
        );
        // "WATER DEPTH" is not a domain; "TWT" must not match inside "TWTX".
        assert!(find("C 1 WATER DEPTH 95 M\nC 2 TWTX", TIME_PHRASES).is_empty());
        assert!(find("C 1 WATER DEPTH 95 M", DEPTH_PHRASES).is_empty());
        assert_eq!(find("c 4 z: twt (ms)", WEAK_TIME_WORDS)[0].phrase, "TWT");
        assert_eq!(
            find("C 9 Sample interval 4 msec", WEAK_TIME_WORDS)[0].line,
            1
        );
        assert_eq!(
            find("C 2 two-way time", TIME_PHRASES)[0].phrase,
            "TWO WAY TIME"
        );
        // A lone "M" is no unit word.
        assert!(find("C 3 WATER DEPTH 120 M", METRE_WORDS).is_empty());
        assert_eq!(find("C 5 DEPTH IN FEET", FEET_WORDS)[0].phrase, "FEET");
    }
}
