//! Matching engine (paper §III-B, §III-C, Algorithm 1): associates a query landmark with
//! database landmarks.
//!
//! Per landmark, once ([`PreparedLandmark`]): nuisance normalisation ([`normalise`], Eq. 2),
//! keypoints on the normalised field ([`keypoints`]), Gaussian-weighted patches packed as a
//! GEMM factor ([`patches`]). Per pair ([`compare`]): for both headings ([`heading`]) the
//! mutually observed overlap, all patch distances (two GEMMs), unique mutual nearest
//! neighbours ([`correspondences`]), rigid consensus in the `(z, p)` chart ([`verify`]) giving
//! `K`, `S = 2K / (N_i + N_j)` and `(dz, dp)`; the heading with more inliers wins. Per query
//! ([`database`]): eligibility, rayon over candidates, acceptance iff `K >= min_inliers` and
//! the best score is unique. [`synthetic`] generates realistic descriptors for tests and benches.

// Grid code indexes several parallel arrays by (row, col); ranges read best there.
#![allow(clippy::needless_range_loop)]

pub mod change;
pub mod correspondences;
pub mod database;
pub mod heading;
pub mod keypoints;
pub mod normalise;
pub mod null_model;
pub mod patch_distances;
pub mod patches;
pub mod retrieval;
pub mod synthetic;
pub mod verify;

use std::cell::{Cell, OnceCell};
use std::sync::{Arc, OnceLock};

use serde::{Deserialize, Serialize};

use crate::config::MatchingConfig;
use crate::error::{DecodError, Result};
use crate::landmark::Landmark;
use crate::spill::{Held, Record, Spill};

pub use database::{LandmarkDatabase, QueryResult};
pub use heading::Heading;
use keypoints::{AtCell, KeptCell};
use normalise::Normalisation;
use patch_distances::{Distances, PatchFactor, QueryPatches};
use patches::{CandidatePatches, PatchShape};
use retrieval::QuantisedQuery;
use verify::Correspondence;

/// Why a pair or a query was not accepted (reported, never silent).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Rejection {
    /// The candidate is too close in time to the query or shares scans with it (§IV-A).
    Ineligible,
    /// The database holds no eligible candidate for this query.
    NoCandidates,
    /// Fewer mutually observed cells than `min_overlap_fraction` under both headings.
    InsufficientOverlap,
    /// Fewer than `min_inliers` verified correspondences.
    TooFewInliers,
    /// The best candidate does not beat the runner-up by `uniqueness_ratio` (aliasing).
    NotUnique,
    /// The null model ([`null_model`]) explains the inliers as chance agreement.
    Chance,
}

impl Rejection {
    /// A stable snake_case name (CSV columns, JSON, Python).
    pub fn as_str(self) -> &'static str {
        match self {
            Rejection::Ineligible => "ineligible",
            Rejection::NoCandidates => "no_candidates",
            Rejection::InsufficientOverlap => "insufficient_overlap",
            Rejection::TooFewInliers => "too_few_inliers",
            Rejection::NotUnique => "not_unique",
            Rejection::Chance => "chance",
        }
    }
}

/// The comparison of a query landmark with one candidate, under its better heading.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairResult {
    /// Relative heading that won (more inliers, then higher score; ties to `Forward`).
    pub heading: Heading,
    /// Fraction of grid cells observed in both descriptors under that heading.
    pub overlap_fraction: f64,
    /// Keypoints of the query, `N_i`.
    pub query_keypoints: usize,
    /// Keypoints of the candidate, `N_j`.
    pub candidate_keypoints: usize,
    /// Unique mutual nearest-neighbour correspondences before verification.
    pub matches: usize,
    /// Verified inliers `K` (all matches when verification is off).
    pub inliers: usize,
    /// Consensus score `S = 2K / (N_i + N_j)`.
    pub score: f64,
    /// Axial offset, metres: a surface feature at query `z` lies at `z + dz_m` in the
    /// candidate descriptor brought to the query's heading; the query origin's plane is the
    /// candidate's plane at `dz_m` along the query-heading axis.
    pub dz_m: f64,
    /// Circumferential offset (same convention) as a fraction of the circumference,
    /// in `[-0.5, 0.5)`.
    pub dp: f64,
    /// Why the pair is not a loop on its own (overlap, inliers); `None` if it passes.
    pub rejection: Option<Rejection>,
    /// Chance that two unrelated surfaces with these keypoints verify this well
    /// ([`null_model::pair_p_value`]); computed by [`compare`] only (a database query judges
    /// its Top-1 in `QueryResult::chance`), 1 elsewhere.
    #[serde(default = "one")]
    pub chance: f64,
}

fn one() -> f64 {
    1.0
}

/// Per-landmark work done once: normalised field, keypoints, patches.
#[derive(Clone, Debug)]
pub struct PreparedLandmark {
    /// The landmark's fields without its cells ([`Landmark::head`]): a view keeps what it
    /// compares, not the cells it was prepared from, so that a run's landmarks can wait on
    /// disk ([`crate::spill`]) while their views are matched.
    pub head: Arc<Landmark>,
    /// The landmark prepared (in memory or on disk): for what needs its cells again.
    pub source: Held,
    /// Observed mask as a bitset (bit `i` = flat cell `i`), heading 0 (after
    /// [`normalise::smooth_along_p`] filled isolated gaps, if enabled); a query flips it
    /// ([`QuerySide::new`]).
    observed_bits: Vec<u64>,
    /// Keypoints (heading 0), strongest first: their cells.
    pub keypoints: Vec<KeptCell>,
    /// The keypoints' patches (compact; the GEMM factor is built from them per comparison),
    /// in memory or set aside on disk ([`Self::set_aside`]).
    patches: Patches,
    /// Coarse signatures, quantised as the scan reads them: for a query
    /// ([`Self::new_query`]) both headings at a few axial shifts
    /// ([`retrieval::query_signatures`]); for a database entry the first of those only
    /// (forward, unshifted), what the entry is indexed by.
    pub coarse: QuantisedQuery,
    /// Earliest and latest scan stamp of the submap (eligibility's fast path).
    scan_span: (f64, f64),
}

/// A view's patches: in memory, or on disk while a run's passes are matched ([`crate::spill`]),
/// read back by each comparison that needs them.
#[derive(Clone, Debug)]
enum Patches {
    Memory(Arc<CandidatePatches>),
    Disk(Record),
}

/// The bitset of a `rows x cols` mask under the heading flip (flat reversal): what a query
/// compares under [`Heading::Reversed`], derived once per query rather than kept per view.
fn flipped(bits: &[u64], (rows, cols): (usize, usize)) -> Vec<u64> {
    let n = rows * cols;
    if n % 64 == 0 && bits.len() == n / 64 {
        // Whole words (every grid of the presets): the words in reverse, each reversed.
        return bits.iter().rev().map(|w| w.reverse_bits()).collect();
    }
    let bit = |i: usize| bits.get(i / 64).is_some_and(|w| w >> (i % 64) & 1 == 1);
    bitset((0..n).rev().map(bit))
}

fn bitset(bits: impl Iterator<Item = bool>) -> Vec<u64> {
    let mut out = Vec::new();
    for (i, b) in bits.enumerate() {
        if i % 64 == 0 {
            out.push(0);
        }
        if b && let Some(w) = out.last_mut() {
            *w |= 1 << (i % 64);
        }
    }
    out
}

impl PreparedLandmark {
    /// Normalises, detects keypoints and packs patches (validates the landmark first); keeps
    /// the forward coarse signature only, all a database entry is indexed by.
    pub fn new(
        landmark: impl Into<Held>,
        cfg: &MatchingConfig,
        shape: &PatchShape,
    ) -> Result<Self> {
        Self::prepare(landmark.into(), cfg, shape, false)
    }

    /// [`Self::new`] for a query: with all of its coarse signatures
    /// ([`retrieval::query_signatures`], both headings at every shift), computed beside the
    /// keypoints and patches (`rayon::join`): they took a tenth of a coarse query on one core.
    pub fn new_query(
        landmark: impl Into<Held>,
        cfg: &MatchingConfig,
        shape: &PatchShape,
    ) -> Result<Self> {
        Self::prepare(landmark.into(), cfg, shape, true)
    }

    fn prepare(
        source: Held,
        cfg: &MatchingConfig,
        shape: &PatchShape,
        query: bool,
    ) -> Result<Self> {
        let landmark = source.landmark()?;
        landmark.validate()?;
        let d = &landmark.descriptor;
        let grid = (d.rows, d.cols);
        // Keypoints always come from the offsets' magnitudes; the sign-only ablation changes
        // what the patches compare, not where they are (a sign field has no extrema).
        let raw = normalise::normalised_field(d, Normalisation::from_config(cfg), false);
        // Arc length to columns (validate() guarantees a positive perimeter).
        let sigma_p_cells = if d.perimeter_m > 0.0 {
            cfg.field_smoothing_sigma_m * d.cols as f64 / d.perimeter_m
        } else {
            0.0
        };
        let (field, observed) =
            normalise::smooth_along_p(&raw, &d.observed, d.rows, d.cols, sigma_p_cells);
        let compared: Vec<f64> = if cfg.sign_only {
            field
                .iter()
                .zip(&observed)
                .map(|(&v, &o)| if !o || v == 0.0 { 0.0 } else { v.signum() })
                .collect()
        } else {
            field.clone()
        };
        let signatures = || {
            QuantisedQuery::new(&if query {
                retrieval::query_signatures(&compared, &observed, d.rows, d.cols)
            } else {
                vec![retrieval::signature(&compared, &observed, d.rows, d.cols)]
            })
        };
        let keypoints_and_patches = || {
            let keypoints = keypoints::detect(&field, &observed, d.rows, d.cols, cfg, |r, c| {
                shape.coverage(&observed, grid, r, c)
            });
            let patches = CandidatePatches::new(shape, &compared, &observed, grid, &keypoints);
            (keypoints.iter().map(KeptCell::from).collect(), patches)
        };
        let ((keypoints, patches), coarse) = if query {
            rayon::join(keypoints_and_patches, signatures)
        } else {
            (keypoints_and_patches(), signatures())
        };
        let scan_span = landmark
            .scan_stamps
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &s| {
                (lo.min(s), hi.max(s))
            });
        Ok(Self {
            coarse,
            scan_span,
            observed_bits: bitset(observed.iter().copied()),
            keypoints,
            patches: Patches::Memory(Arc::new(patches)),
            head: source.stripped(),
            source,
        })
    }

    /// The keypoints' patches, read back where they are on disk.
    pub fn patches(&self) -> Result<Arc<CandidatePatches>> {
        match &self.patches {
            Patches::Memory(p) => Ok(Arc::clone(p)),
            Patches::Disk(r) => CandidatePatches::decode(&r.bytes()?, r.path()).map(Arc::new),
        }
    }

    /// Moves the patches (the compared field and the keypoints' centres, about 17 KB of a
    /// view's 22) into `spill`: each comparison then reads them back (about 17 KB against a
    /// pair's 0.2 ms of products), and memory holds the rest of the view.
    pub fn set_aside(&mut self, spill: &Arc<Spill>) -> Result<()> {
        if let Patches::Memory(p) = &self.patches {
            let mut bytes = Vec::with_capacity(p.heap_bytes() + 64);
            p.encode(&mut bytes);
            self.patches = Patches::Disk(spill.append(&bytes)?);
        }
        Ok(())
    }

    /// Grid size `(rows, cols)`.
    pub fn grid(&self) -> (usize, usize) {
        (self.head.descriptor.rows, self.head.descriptor.cols)
    }

    /// Whether the two submaps' scan-stamp ranges overlap (if not, they share no scan).
    pub(crate) fn scans_may_overlap(&self, other: &PreparedLandmark) -> bool {
        self.scan_span.0 <= other.scan_span.1 && other.scan_span.0 <= self.scan_span.1
    }

    /// Approximate heap bytes held by this prepared landmark: its head, the landmark's cells
    /// where it is in memory (descriptor, mask, normals, contour, scan stamps), the patches,
    /// masks and signatures.
    pub fn heap_bytes(&self) -> usize {
        let bytes = |l: &Landmark| {
            let d = &l.descriptor;
            let f64s = d.normal_e1.len() + d.normal_e2.len();
            8 * (f64s + l.scan_stamps.len() + 2 * l.contour_e1e2_m.len())
                + 4 * d.offsets_m.len()
                + d.observed.len()
                + std::mem::size_of::<Landmark>()
        };
        let landmark = bytes(&self.head)
            + match &self.source {
                Held::Memory(l) => bytes(l),
                Held::Disk(_) => 0,
            };
        let patches = match &self.patches {
            Patches::Memory(p) => p.heap_bytes(),
            Patches::Disk(_) => 0,
        };
        let bits = 8 * self.observed_bits.len();
        let keypoints = self.keypoints.len() * std::mem::size_of::<KeptCell>();
        let coarse = self.coarse.heap_bytes();
        landmark + patches + bits + keypoints + coarse
    }
}

/// The query side of a prepared landmark: its patch factors under each heading, built on
/// first use (within a run the heading prior usually asks for one of them only), and its
/// flipped mask.
#[derive(Clone, Debug)]
pub struct QuerySide {
    sides: [OnceLock<QueryPatches>; 2],
    flipped_bits: Vec<u64>,
    /// The query's patches (read back once where they are on disk).
    patches: Arc<CandidatePatches>,
}

impl QuerySide {
    /// The query side of `p` (its factors are built by the comparisons that need them).
    pub fn new(p: &PreparedLandmark) -> Result<Self> {
        Ok(Self {
            sides: [OnceLock::new(), OnceLock::new()],
            flipped_bits: flipped(&p.observed_bits, p.grid()),
            patches: p.patches()?,
        })
    }

    /// The query factors under `heading`.
    fn patches(&self, shape: &PatchShape, heading: Heading) -> &QueryPatches {
        let flipped = heading == Heading::Reversed;
        self.sides[usize::from(flipped)]
            .get_or_init(|| QueryPatches::from_candidate(shape, &self.patches, flipped))
    }
}

/// Checks that two landmarks share a grid (the database and `compare` refuse mixed grids).
pub fn check_grids(query: &Landmark, candidate: &Landmark) -> Result<()> {
    let (q, c) = (&query.descriptor, &candidate.descriptor);
    if (q.rows, q.cols) != (c.rows, c.cols) {
        return Err(DecodError::invalid(
            "candidate descriptor",
            format!(
                "grid {}x{} differs from the query's {}x{}",
                c.rows, c.cols, q.rows, q.cols
            ),
        ));
    }
    Ok(())
}

/// Compares two landmarks under both headings (paper Algorithm 1, lines 6–10).
pub fn compare(query: &Landmark, candidate: &Landmark, cfg: &MatchingConfig) -> Result<PairResult> {
    check_grids(query, candidate)?;
    let shape = PatchShape::new(cfg);
    let q = PreparedLandmark::new(Arc::new(query.clone()), cfg, &shape)?;
    let c = PreparedLandmark::new(Arc::new(candidate.clone()), cfg, &shape)?;
    compare_with_chance(&q, &c, cfg, &shape)
}

/// Many comparisons among `landmarks` at once: `pairs` of (query, candidate) indices, each
/// landmark prepared once, pairs in parallel (rayon). The within-pass association of views
/// (boundary tracks) compares hundreds of pairs of few landmarks: preparing each landmark
/// per pair cost more than the comparisons. An index out of range is an error naming it.
///
/// `same_heading`: compare under 0 degrees only (beyond the paper). Views of one pass share
/// the sensor's heading, so a within-pass pair is judged as it was seen: before, a pair whose
/// turned-round comparison scored higher was refused as a link even when the unturned one
/// passed on its own. In the generalisation matrix this changed only shield tunnel runs: 18
/// more loops (7,071 -> 7,089), none wrong, registry joints within 1 % in one more run.
pub fn compare_pairs(
    landmarks: &[Held],
    pairs: &[(usize, usize)],
    cfg: &MatchingConfig,
    same_heading: bool,
) -> Result<Vec<PairResult>> {
    use rayon::prelude::*;
    check_pair_indices(pairs, landmarks.len())?;
    for &(i, j) in pairs {
        check_grids(landmarks[i].head(), landmarks[j].head())?;
    }
    let mut used = vec![false; landmarks.len()];
    for &(i, j) in pairs {
        used[i] = true;
        used[j] = true;
    }
    let shape = PatchShape::new(cfg);
    let prepared = landmarks
        .par_iter()
        .zip(used.par_iter())
        .map(|(l, &u)| {
            u.then(|| PreparedLandmark::new(l.clone(), cfg, &shape))
                .transpose()
        })
        .collect::<Result<Vec<_>>>()?;
    let get = |i: usize| prepared.get(i).and_then(Option::as_ref);
    compare_prepared_pairs(get, pairs, cfg, &shape, same_heading)
}

/// Every landmark of a run prepared once, as a query (all coarse signatures), in parallel:
/// the within-pass comparisons ([`compare_view_pairs`]), the database entries
/// ([`LandmarkDatabase::extend_prepared`]) and the queries
/// ([`LandmarkDatabase::query_batch_prepared`]) then share them (beyond the paper: each
/// landmark was prepared twice per round, ~0.1 s of a 64-beam round). The landmarks must
/// share one grid; those on disk ([`crate::spill`]) are read back one at a time, and their
/// views keep what they compare, not the cells. With `spill`, each view's patches go there
/// as soon as it is prepared ([`PreparedLandmark::set_aside`]).
pub fn prepare_views(
    landmarks: &[Held],
    cfg: &MatchingConfig,
    spill: Option<&Arc<Spill>>,
) -> Result<Vec<Arc<PreparedLandmark>>> {
    use rayon::prelude::*;
    for pair in landmarks.windows(2) {
        check_grids(pair[0].head(), pair[1].head())?;
    }
    let shape = PatchShape::new(cfg);
    landmarks
        .par_iter()
        .map(|l| {
            let mut view = PreparedLandmark::new_query(l.clone(), cfg, &shape)?;
            if let Some(spill) = spill {
                view.set_aside(spill)?;
            }
            Ok(Arc::new(view))
        })
        .collect()
}

/// [`compare_pairs`] on views from [`prepare_views`] under the same `cfg`.
pub fn compare_view_pairs(
    views: &[Arc<PreparedLandmark>],
    pairs: &[(usize, usize)],
    cfg: &MatchingConfig,
    same_heading: bool,
) -> Result<Vec<PairResult>> {
    check_pair_indices(pairs, views.len())?;
    let shape = PatchShape::new(cfg);
    compare_prepared_pairs(
        |i| views.get(i).map(|v| &**v),
        pairs,
        cfg,
        &shape,
        same_heading,
    )
}

/// An error naming the first pair with an index beyond `n` landmarks.
fn check_pair_indices(pairs: &[(usize, usize)], n: usize) -> Result<()> {
    match pairs.iter().find(|&&(i, j)| i >= n || j >= n) {
        Some(&(i, j)) => Err(DecodError::invalid(
            "pairs",
            format!("({i}, {j}) out of range for {n} landmarks"),
        )),
        None => Ok(()),
    }
}

/// The pairs' comparisons, in their order, on prepared landmarks (`get(i)`), in parallel.
/// Pairs are grouped by their query: its query-side factors are built once per query, not
/// once per pair (a track's view is compared with each of its neighbours).
fn compare_prepared_pairs<'a>(
    get: impl Fn(usize) -> Option<&'a PreparedLandmark> + Sync,
    pairs: &[(usize, usize)],
    cfg: &MatchingConfig,
    shape: &PatchShape,
    same_heading: bool,
) -> Result<Vec<PairResult>> {
    use rayon::prelude::*;
    let n = pairs.iter().map(|&(i, _)| i + 1).max().unwrap_or(0);
    let mut by_query: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (k, &(i, _)) in pairs.iter().enumerate() {
        by_query[i].push(k);
    }
    let found: Vec<Vec<(usize, PairResult)>> = by_query
        .par_iter()
        .enumerate()
        .filter(|(_, ks)| !ks.is_empty())
        .map(|(i, ks)| {
            let Some(q) = get(i) else {
                return Ok(Vec::new());
            };
            let side = QuerySide::new(q)?;
            ks.iter()
                .filter_map(|&k| {
                    let c = get(pairs[k].1)?;
                    let pair = if same_heading {
                        compare_heading(
                            q,
                            &side,
                            &CandidateFactor::new(c, shape),
                            Heading::Forward,
                            cfg,
                        )
                    } else {
                        compare_prepared(q, &side, c, cfg, shape)
                    };
                    Some(pair.map(|mut pair| {
                        if cfg.verification {
                            pair.chance = pair_chance(q, c, &pair, cfg);
                        }
                        (k, pair)
                    }))
                })
                .collect()
        })
        .collect::<Result<_>>()?;
    let mut out: Vec<Option<PairResult>> = vec![None; pairs.len()];
    for (k, pair) in found.into_iter().flatten() {
        out[k] = Some(pair);
    }
    Ok(out.into_iter().flatten().collect())
}

/// [`compare_prepared`] plus the pair's null-model chance.
fn compare_with_chance(
    q: &PreparedLandmark,
    c: &PreparedLandmark,
    cfg: &MatchingConfig,
    shape: &PatchShape,
) -> Result<PairResult> {
    let side = QuerySide::new(q)?;
    let mut pair = compare_prepared(q, &side, c, cfg, shape)?;
    if cfg.verification {
        pair.chance = pair_chance(q, c, &pair, cfg);
    }
    Ok(pair)
}

/// The null model's chance for `pair` of prepared landmarks ([`null_model::pair_p_value`]).
pub(crate) fn pair_chance(
    q: &PreparedLandmark,
    c: &PreparedLandmark,
    pair: &PairResult,
    cfg: &MatchingConfig,
) -> f64 {
    null_model::pair_p_value(
        &q.keypoints,
        &c.keypoints,
        pair.heading,
        q.grid(),
        pair.matches,
        pair.inliers,
        cfg,
    )
}

/// The pairwise part on prepared landmarks (grids already checked).
pub fn compare_prepared(
    q: &PreparedLandmark,
    side: &QuerySide,
    c: &PreparedLandmark,
    cfg: &MatchingConfig,
    shape: &PatchShape,
) -> Result<PairResult> {
    compare_prepared_in(q, side, c, &Heading::BOTH, cfg, shape)
}

/// [`compare_prepared`] under `headings` only (one of them: [`heading::prior`]; both: the
/// better, as [`compare_prepared`]).
pub fn compare_prepared_in(
    q: &PreparedLandmark,
    side: &QuerySide,
    c: &PreparedLandmark,
    headings: &[Heading],
    cfg: &MatchingConfig,
    shape: &PatchShape,
) -> Result<PairResult> {
    let factor = CandidateFactor::new(c, shape);
    if let [only] = headings {
        return compare_heading(q, side, &factor, *only, cfg);
    }
    let forward = compare_heading(q, side, &factor, Heading::Forward, cfg)?;
    let reversed = compare_heading(q, side, &factor, Heading::Reversed, cfg)?;
    let key = |r: &PairResult| {
        (
            r.rejection != Some(Rejection::InsufficientOverlap),
            r.inliers,
        )
    };
    let better_reversed = key(&reversed) > key(&forward)
        || (key(&reversed) == key(&forward) && reversed.score > forward.score)
        || (forward.rejection == Some(Rejection::InsufficientOverlap)
            && reversed.rejection == Some(Rejection::InsufficientOverlap)
            && reversed.overlap_fraction > forward.overlap_fraction);
    Ok(if better_reversed { reversed } else { forward })
}

/// One heading. Overlap (the paper is silent on its threshold): mutually observed cells over
/// all grid cells, rejected below `min_overlap_fraction` (0.25). On synthetic views the
/// lower-half-occluded pair has overlap 0.42 and K = 13, a one-third view 0.33 and K = 7, so
/// 0.25 only removes fragments that could not reach K = 9 anyway.
fn compare_heading(
    q: &PreparedLandmark,
    side: &QuerySide,
    factor: &CandidateFactor<'_>,
    heading: Heading,
    cfg: &MatchingConfig,
) -> Result<PairResult> {
    let (c, shape) = (factor.landmark, factor.shape);
    let (rows, cols) = q.grid();
    let q_bits = match heading {
        Heading::Forward => &q.observed_bits,
        Heading::Reversed => &side.flipped_bits,
    };
    let mutual: u32 = q_bits
        .iter()
        .zip(&c.observed_bits)
        .map(|(a, b)| (a & b).count_ones())
        .sum();
    let overlap_fraction = f64::from(mutual) / (rows * cols) as f64;
    let (ni, nj) = (q.keypoints.len(), c.keypoints.len());
    let mut result = PairResult {
        heading,
        overlap_fraction,
        query_keypoints: ni,
        candidate_keypoints: nj,
        matches: 0,
        inliers: 0,
        score: 0.0,
        dz_m: 0.0,
        dp: 0.0,
        rejection: None,
        chance: 1.0,
    };
    if overlap_fraction < cfg.min_overlap_fraction {
        result.rejection = Some(Rejection::InsufficientOverlap);
        return Ok(result);
    }
    let qp = side.patches(shape, heading);
    let dist = patch_distances::distances(shape, qp, factor.get()?, cfg.min_patch_overlap_fraction);
    let matches = keypoint_correspondences(q, c, &dist, heading);
    let consensus = if cfg.verification {
        verify::consensus(&matches, cols, cfg)
    } else {
        verify::no_consensus(&matches, cols)
    };
    // Offsets were measured between the flipped query and the candidate; in the query's
    // heading they change sign (see `PairResult::dz_m`).
    let sign = match heading {
        Heading::Forward => 1.0,
        Heading::Reversed => -1.0,
    };
    result.matches = matches.len();
    result.inliers = consensus.inliers;
    result.score = if ni + nj > 0 {
        2.0 * consensus.inliers as f64 / (ni + nj) as f64
    } else {
        0.0
    };
    result.dz_m = sign * consensus.dz_cells * q.head.descriptor.cell_z_m;
    let dp = sign * consensus.dp_cells / cols as f64;
    result.dp = if dp >= 0.5 { dp - 1.0 } else { dp };
    if cfg.verification && consensus.inliers < pair_floor(cfg) {
        result.rejection = Some(Rejection::TooFewInliers);
    }
    Ok(result)
}

thread_local! {
    /// The buffer [`CandidateFactor`]s build their factor in, one per thread (a rayon worker
    /// compares one pair at a time): reused, so a comparison allocates nothing for it.
    static FACTOR_BUFFER: Cell<Option<PatchFactor>> = const { Cell::new(None) };
}

/// A candidate's GEMM factor ([`PatchFactor::fill`]), built by the first
/// heading whose comparison gets past the overlap test and shared by the other, in the
/// thread's [`FACTOR_BUFFER`] (given back on drop).
struct CandidateFactor<'a> {
    landmark: &'a PreparedLandmark,
    shape: &'a PatchShape,
    buffer: OnceCell<PatchFactor>,
}

impl<'a> CandidateFactor<'a> {
    fn new(landmark: &'a PreparedLandmark, shape: &'a PatchShape) -> Self {
        Self {
            landmark,
            shape,
            buffer: OnceCell::new(),
        }
    }

    fn get(&self) -> Result<&PatchFactor> {
        if let Some(factor) = self.buffer.get() {
            return Ok(factor);
        }
        let patches = self.landmark.patches()?;
        Ok(self.buffer.get_or_init(|| {
            let mut buf = FACTOR_BUFFER.take().unwrap_or_default();
            buf.fill(self.shape, &patches);
            buf
        }))
    }
}

impl Drop for CandidateFactor<'_> {
    fn drop(&mut self) {
        if let Some(buf) = self.buffer.take() {
            FACTOR_BUFFER.set(Some(buf));
        }
    }
}

/// The mutual nearest keypoint pairs of the patch distances `dist` (query x candidate), the
/// query's cells in the candidate's heading (flipped for [`Heading::Reversed`]).
fn keypoint_correspondences(
    q: &PreparedLandmark,
    c: &PreparedLandmark,
    dist: &Distances<'_>,
    heading: Heading,
) -> Vec<Correspondence> {
    let (rows, cols) = q.grid();
    dist.mutual_nearest()
        .iter()
        .map(|&(i, j)| {
            let (row, col) = q.keypoints[i].cell();
            let query = match heading {
                Heading::Forward => (row, col),
                Heading::Reversed => heading::flip_cell(row, col, rows, cols),
            };
            Correspondence {
                query,
                candidate: c.keypoints[j].cell(),
            }
        })
        .collect()
}

/// The inlier count below which a pair is rejected on its own: `min_inliers` under the
/// paper's fixed rule; under the null model ([`null_model`]) `min_inliers_floor` (never
/// below 3, the fewest correspondences that say more than "one translation fits two
/// points"), the rest being the null model's decision per query.
pub fn pair_floor(cfg: &MatchingConfig) -> usize {
    if cfg.acceptance == "null_model" {
        cfg.min_inliers_floor.max(3)
    } else {
        cfg.min_inliers
    }
}

#[cfg(test)]
mod tests;
