//! How good the matches are, against a known true offset: the reference study's matching
//! efficiency r (its equation 2) and mean average precision MAP (its equation 3).
//!
//! Definitions used here (the matches are the two-way matches, RANSAC's input, so the
//! figures judge detection and matching, not RANSAC's clean-up):
//! - A match is **correct** when its displacement (feature position in a minus feature
//!   position in b, as detected, not refined) lies within `tolerance_px` (1 px, Euclidean) of
//!   the true offset (b's true origin minus a's).
//! - **r** = correct matches / all matches of the pair (`None` without matches).
//! - **AP** of a pair: rank its matches by score (NCC for Harris, descriptor similarity for
//!   SIFT), best first; at the rank k of each correct match take the precision
//!   P(k) = correct matches among the first k / k; AP = the mean of those precisions over the
//!   correct matches (0 when there is none; `None` without matches).
//! - **MAP** = the mean of AP over the pairs that have an AP; the aggregate r is the mean of r
//!   over the same pairs.

use surfstream_core::record::FeatureSummaryRecord;

/// One match as the figures see it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RankedMatch {
    /// `a_px - b_px`, px.
    pub displacement_px: [f64; 2],
    /// Larger = better ranked.
    pub score: f64,
}

pub use surfstream_core::record::MatchQuality;

use crate::feature_match::FeatureRegistration;

// The figures judge the matcher's output: this module imports feature_match, never the
// other way round.
impl FeatureRegistration {
    /// r and AP of the two-way matches against a true offset (see the module documentation).
    pub fn quality(&self, true_offset_px: [f64; 2], tolerance_px: f64) -> MatchQuality {
        let ranked: Vec<RankedMatch> = self
            .matches
            .iter()
            .map(|m| RankedMatch {
                displacement_px: m.displacement_px,
                score: m.score,
            })
            .collect();
        match_quality(&ranked, true_offset_px, tolerance_px)
    }
}

/// Whether a displacement is within `tolerance_px` of the truth.
pub fn is_correct(displacement_px: [f64; 2], true_offset_px: [f64; 2], tolerance_px: f64) -> bool {
    let dx = displacement_px[0] - true_offset_px[0];
    let dy = displacement_px[1] - true_offset_px[1];
    (dx * dx + dy * dy).sqrt() <= tolerance_px
}

/// r and AP of one pair's matches against its true offset.
pub fn match_quality(
    matches: &[RankedMatch],
    true_offset_px: [f64; 2],
    tolerance_px: f64,
) -> MatchQuality {
    let mut ranked: Vec<&RankedMatch> = matches.iter().collect();
    // Stable: equal scores keep their given order.
    ranked.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut correct = 0usize;
    let mut precision_sum = 0.0;
    for (k, m) in ranked.iter().enumerate() {
        if is_correct(m.displacement_px, true_offset_px, tolerance_px) {
            correct += 1;
            precision_sum += correct as f64 / (k + 1) as f64;
        }
    }
    let n = matches.len();
    MatchQuality {
        matches: n,
        correct,
        r: (n > 0).then(|| correct as f64 / n as f64),
        average_precision: (n > 0).then(|| {
            if correct == 0 {
                0.0
            } else {
                precision_sum / correct as f64
            }
        }),
        tolerance_px,
    }
}

/// Mean r and MAP over pairs (pairs without matches are left out): `(mean r, MAP, pairs)`.
pub fn aggregate(qualities: &[MatchQuality]) -> (Option<f64>, Option<f64>, usize) {
    let with: Vec<&MatchQuality> = qualities.iter().filter(|q| q.r.is_some()).collect();
    if with.is_empty() {
        return (None, None, 0);
    }
    let n = with.len() as f64;
    let r = with.iter().filter_map(|q| q.r).sum::<f64>() / n;
    let map = with.iter().filter_map(|q| q.average_precision).sum::<f64>() / n;
    (Some(r), Some(map), with.len())
}

/// Tolerance of a correct match, px (see the module documentation).
pub const CORRECT_MATCH_TOLERANCE_PX: f64 = 1.0;

/// r and AP of every feature-matched pair against a truth file, and the run's summary
/// (run.json `global.features`): `pairs` lists (a's acquisition index, b's, the outcome).
/// A pair whose tiles the file does not list gets `None`. Errors name the file.
pub fn score_feature_pairs(
    truth_path: &std::path::Path,
    pairs: &[(u64, u64, &FeatureRegistration)],
) -> Result<(Vec<Option<MatchQuality>>, FeatureSummaryRecord), surfstream_io::truth::TruthError> {
    let truth = surfstream_io::truth::ScanTruth::read(truth_path)?;
    let per_pair: Vec<Option<MatchQuality>> = pairs
        .iter()
        .map(|(a, b, f)| {
            truth
                .true_offset_px(*a, *b)
                .map(|t| f.quality(t, CORRECT_MATCH_TOLERANCE_PX))
        })
        .collect();
    let scored: Vec<MatchQuality> = per_pair.iter().flatten().copied().collect();
    let (r, map, n) = aggregate(&scored);
    let summary = FeatureSummaryRecord {
        truth: truth_path.display().to_string(),
        pairs_with_truth: scored.len(),
        pairs_with_matches: n,
        mean_r: r,
        map,
        correct_match_tolerance_px: CORRECT_MATCH_TOLERANCE_PX,
    };
    Ok((per_pair, summary))
}
