//! The landmark database and queries (paper Algorithm 1, §IV-A protocol).
//!
//! Landmarks are prepared once when added (normalisation, keypoints, patches), so a
//! query only runs the pairwise part, over all eligible entries in parallel (rayon).
//!
//! Eligibility (paper §IV-A): query and candidate submaps at least `min_time_separation_s`
//! apart and sharing no scan stamp.
//!
//! Acceptance: the best candidate (highest `S`, then `K`, then lowest index) is accepted iff
//! `K >= min_inliers` AND it is unique: `S_best >= uniqueness_ratio * S_runner_up` and
//! `K_best - K_runner_up >= uniqueness_sigma * sqrt(K_best + K_runner_up)`, where the
//! runner-up is the best score among all OTHER eligible candidates (optionally not those
//! within `runner_up_exclusion_s` of the best, which may be a second view of the same joint,
//! nor those that put the query where the best puts it, `runner_up_same_place_rows`).
//! Identical precast joints score as high as the true joint (often higher), so no absolute
//! threshold can reject aliasing; only a margin over the runner-up can. Measured on the
//! synthetic sets (tunnel grid, random views): an aliased corridor (4 identical joints,
//! different noise and views, 60 queries) gives best/runner-up ratios 1.00–1.72 (median
//! ~1.15; 22 of 60 above 1.2), while true loops among 50 distinct joints of one pipe give
//! 3.7–15.5 (runner-ups at K <= 3, true K 8–31, mean 20). `uniqueness_ratio = 2.0` rejects
//! all of the former and keeps all of the latter. A K margin adds nothing here: at fixed
//! `N_i + N_j` the score ratio is the K ratio.
//!
//! Save/load: JSON `{format, version, config, landmarks}`; the prepared data is rebuilt on load
//! (it depends on the config). A file of another format or version is a
//! [`DecodError::Database`] naming both versions.

use std::path::Path;
use std::sync::Arc;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::patches::PatchShape;
use super::retrieval::CoarseIndex;
use super::{
    Heading, PairResult, PreparedLandmark, QuerySide, Rejection, check_grids, compare_prepared_in,
    heading, null_model,
};
use crate::config::MatchingConfig;
use crate::error::{DecodError, Result};
use crate::landmark::Landmark;
use crate::spill::{Held, Spill};

/// Format name written into saved databases.
pub const FORMAT_NAME: &str = "decod-landmark-database";
/// Current format version; loading any other version is an error.
pub const FORMAT_VERSION: u32 = 1;

/// Everything the 5-DoF factor and an explanation need about one query.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QueryResult {
    /// Query submap stamp, seconds.
    pub query_stamp: f64,
    /// Query landmark origin in its submap frame, metres.
    pub query_origin_in_submap: [f64; 3],
    /// Query corridor axis in its submap frame.
    pub query_axis_in_submap: [f64; 3],
    /// Database index of the best candidate (`None` if no candidate was eligible).
    pub candidate_index: Option<usize>,
    /// Best candidate's submap stamp (NaN if none).
    pub candidate_stamp: f64,
    /// Best candidate's origin in its submap frame (zeros if none).
    pub candidate_origin_in_submap: [f64; 3],
    /// Best candidate's axis in its submap frame (zeros if none).
    pub candidate_axis_in_submap: [f64; 3],
    /// The best pair (heading, K, S, offsets, its own rejection if any).
    pub pair: Option<PairResult>,
    /// Accepted as a loop closure.
    pub accepted: bool,
    /// Why not, when not accepted.
    pub rejection: Option<Rejection>,
    /// Score of the best OTHER eligible candidate (0 if none): the uniqueness reference.
    pub runner_up_score: f64,
    /// Inliers of that runner-up.
    pub runner_up_inliers: usize,
    /// Its database index.
    pub runner_up_index: Option<usize>,
    /// Number of eligible candidates compared.
    pub eligible: usize,
    /// Family-wise chance that the best candidate's inliers are chance agreement
    /// (`null_model`); 1 when not computed.
    #[serde(default = "one")]
    pub chance: f64,
    /// The same for the runner-up (1 when there is none).
    #[serde(default = "one")]
    pub runner_up_chance: f64,
}

fn one() -> f64 {
    1.0
}

impl QueryResult {
    /// Relative heading of the best pair (Forward if none).
    pub fn heading(&self) -> Heading {
        self.pair.as_ref().map_or(Heading::Forward, |p| p.heading)
    }
}

/// Saved form of a database.
#[derive(Serialize, Deserialize)]
struct SavedDatabase {
    format: String,
    version: u32,
    config: Option<MatchingConfig>,
    landmarks: Vec<Landmark>,
    /// Physical boundary ids (absent in files written before boundary views: one each).
    #[serde(default)]
    boundaries: Option<Vec<u64>>,
    /// Where each view's boundary lies in the database's frame (absent in older files, and
    /// `null` for a view placed nowhere): the coarse stage's neighbours.
    #[serde(default)]
    positions: Option<Vec<Option<[f64; 3]>>>,
}

/// A set of prepared landmarks that queries run against.
#[derive(Clone, Debug)]
pub struct LandmarkDatabase {
    config: MatchingConfig,
    shape: PatchShape,
    /// Shared with the run's prepared views (`super::prepare_views`) when stored from them.
    entries: Vec<Arc<PreparedLandmark>>,
    /// Physical boundary of each entry: views sharing an id are one candidate, never each
    /// other's runner-up, and count once among the candidates compared.
    boundaries: Vec<u64>,
    /// The entries' forward coarse signatures, contiguous ([`super::retrieval`]).
    coarse: CoarseIndex,
    /// Each entry's boundary origin in the database's frame (NaN when not placed): the
    /// coarse short list is widened by the entries near its own ([`Self::candidates`]).
    positions: Vec<[f64; 3]>,
    /// Each entry's corridor axis in the same frame (NaN when not set): with a query's own,
    /// the heading the odometry allows ([`super::heading::prior`], [`Self::set_directions`]).
    directions: Vec<[f64; 3]>,
    /// The distinct boundary ids (the null model's family when every entry is eligible,
    /// without sorting 10,000 ids per query).
    distinct: std::collections::HashSet<u64>,
}

/// Which database entries a query may be compared with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Eligibility {
    /// Within one run (paper §IV-A): at least `min_time_separation_s` apart, no shared scan.
    WithinRun,
    /// Against an earlier survey: every entry (stamps of two sessions are unrelated).
    CrossSession,
    /// Within one run, between its passes (batch mode: the return pass queries a database of
    /// the outbound pass): no shared scan, but no time separation either. The split already
    /// keeps a pass's own views of a boundary apart; the separation would only drop the
    /// boundaries the two passes see within `min_time_separation_s` of each other, those near
    /// the turnaround (with a forward-looking sensor in a wide tunnel, 14 m of it).
    AcrossPasses,
}

/// How one query runs: its corridor axis in the database's frame (the heading prior; `None`:
/// both headings), in parallel or not, and which entries are eligible.
#[derive(Clone, Copy, Debug)]
struct QueryContext {
    direction: Option<[f64; 3]>,
    parallel: bool,
    eligibility: Eligibility,
}

/// `rows[k]` for entry `indices[k]` of `n`: as many rows as indices, every index stored, every
/// value finite (`what` names the argument in the error).
fn check_rows(what: &str, indices: &[usize], rows: &[[f64; 3]], n: usize) -> Result<()> {
    if indices.len() != rows.len() {
        return Err(DecodError::invalid(
            what,
            format!("{} {what} for {} indices", rows.len(), indices.len()),
        ));
    }
    for (&i, p) in indices.iter().zip(rows) {
        if i >= n {
            return Err(DecodError::invalid(
                what,
                format!("index {i} beyond the {n} entries"),
            ));
        }
        if !p.iter().all(|v| v.is_finite()) {
            return Err(DecodError::invalid(
                what,
                format!("entry {i}: {p:?} is not finite"),
            ));
        }
    }
    Ok(())
}

/// Whether the prepared data of `a` is valid for `b` (same normalisation, keypoints, patches).
fn same_preparation(a: &MatchingConfig, b: &MatchingConfig) -> bool {
    a.patch_rows == b.patch_rows
        && a.patch_cols == b.patch_cols
        && a.sigma_z_cells == b.sigma_z_cells
        && a.sigma_p_cells == b.sigma_p_cells
        && a.normalisation == b.normalisation
        && a.sign_only == b.sign_only
        && a.max_keypoints == b.max_keypoints
        && a.keypoint_nms_rows == b.keypoint_nms_rows
        && a.keypoint_nms_cols == b.keypoint_nms_cols
        && a.min_patch_overlap_fraction == b.min_patch_overlap_fraction
}

/// [`eligible`] on prepared landmarks, skipping the scan comparison when the submaps' scan
/// spans do not overlap (the common case; it made the check cost more than the coarse stage).
fn eligible_prepared(q: &PreparedLandmark, c: &PreparedLandmark, cfg: &MatchingConfig) -> bool {
    separated(&q.head, &c.head, cfg) && !shares_scans(q, c)
}

/// Whether two prepared landmarks' submaps share a scan (compared only when their scan spans
/// overlap).
fn shares_scans(q: &PreparedLandmark, c: &PreparedLandmark) -> bool {
    q.scans_may_overlap(c) && share_a_scan(&q.head, &c.head)
}

fn separated(query: &Landmark, candidate: &Landmark, cfg: &MatchingConfig) -> bool {
    (query.submap_stamp - candidate.submap_stamp).abs() >= cfg.min_time_separation_s
}

fn share_a_scan(query: &Landmark, candidate: &Landmark) -> bool {
    query
        .scan_stamps
        .iter()
        .any(|s| candidate.scan_stamps.contains(s))
}

/// Paper §IV-A: at least `min_time_separation_s` apart and no shared scans.
pub fn eligible(query: &Landmark, candidate: &Landmark, cfg: &MatchingConfig) -> bool {
    separated(query, candidate, cfg) && !share_a_scan(query, candidate)
}

impl LandmarkDatabase {
    /// An empty database whose entries are prepared with `config`.
    pub fn new(config: &MatchingConfig) -> Self {
        Self {
            config: config.clone(),
            shape: PatchShape::new(config),
            entries: Vec::new(),
            boundaries: Vec::new(),
            coarse: CoarseIndex::default(),
            positions: Vec::new(),
            directions: Vec::new(),
            distinct: std::collections::HashSet::new(),
        }
    }

    /// Number of landmarks.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The landmark at `index` (in memory, or on disk: [`crate::spill`]).
    pub fn get(&self, index: usize) -> Option<&Held> {
        self.entries.get(index).map(|e| &e.source)
    }

    /// The config entries are prepared with.
    pub fn config(&self) -> &MatchingConfig {
        &self.config
    }

    /// Validates, prepares and stores a landmark; returns its index. All landmarks of a
    /// database share one grid.
    pub fn add(&mut self, landmark: Landmark) -> Result<usize> {
        let id = self.fresh_id();
        self.add_view(landmark, id)
    }

    /// An id no entry uses yet (one past the largest).
    fn fresh_id(&self) -> u64 {
        self.boundaries.iter().max().map_or(0, |m| m + 1)
    }

    /// [`Self::add`] for one view of the physical boundary `boundary` (other views of it may
    /// already be stored or follow).
    pub fn add_view(&mut self, landmark: Landmark, boundary: u64) -> Result<usize> {
        if let Some(first) = self.entries.first() {
            check_grids(&first.head, &landmark)?;
        }
        let prepared = PreparedLandmark::new(Arc::new(landmark), &self.config, &self.shape)?;
        self.coarse.push_first(&prepared.coarse);
        self.entries.push(Arc::new(prepared));
        self.positions.push([f64::NAN; 3]);
        self.directions.push([f64::NAN; 3]);
        self.boundaries.push(boundary);
        self.distinct.insert(boundary);
        Ok(self.entries.len() - 1)
    }

    /// The physical boundary id of every entry.
    pub fn boundaries(&self) -> &[u64] {
        &self.boundaries
    }

    /// Places entries: `positions[k]` is the boundary origin of entry `indices[k]` in one
    /// frame shared by the whole database (a run's odometry, a survey's corrected frame).
    /// Under `retrieval = "coarse"` the short list is widened by the eligible entries within
    /// a descriptor's extent of its own ([`Self::candidates`]); unplaced entries are only
    /// reached through the signature.
    pub fn set_positions(&mut self, indices: &[usize], positions: &[[f64; 3]]) -> Result<()> {
        check_rows("positions", indices, positions, self.entries.len())?;
        for (&i, p) in indices.iter().zip(positions) {
            self.positions[i] = *p;
        }
        Ok(())
    }

    /// Orients entries: `directions[k]` is the corridor axis of entry `indices[k]` (the
    /// landmark's axis, oriented with the sensor's forward) in the frame of
    /// [`Self::set_positions`]. Entries placed and oriented in one frame are compared with
    /// each other by the same-place rule (`runner_up_same_place_rows`), in any frame they
    /// share. A query that brings its own axis in that frame
    /// ([`Self::query_batch_prepared`]) is also compared with such an entry under the heading
    /// the odometry allows only ([`super::heading::prior`]), when the config's
    /// `heading_from_odometry` is on; a re-inspection's queries bring none, since a survey's
    /// corrected frame is not the new run's odometry frame.
    pub fn set_directions(&mut self, indices: &[usize], directions: &[[f64; 3]]) -> Result<()> {
        check_rows("directions", indices, directions, self.entries.len())?;
        if let Some((&i, d)) = indices
            .iter()
            .zip(directions)
            .find(|(_, d)| d.iter().map(|v| v * v).sum::<f64>() == 0.0)
        {
            return Err(DecodError::invalid(
                "directions",
                format!("entry {i}: direction {d:?} is zero"),
            ));
        }
        for (&i, d) in indices.iter().zip(directions) {
            self.directions[i] = *d;
        }
        Ok(())
    }

    /// The entries' positions and directions, for the matcher's geometry.
    fn placement(&self) -> Placement<'_> {
        Placement {
            positions: &self.positions,
            directions: &self.directions,
        }
    }

    /// Each entry's direction (NaN where none was set, [`Self::set_directions`]).
    pub fn directions(&self) -> &[[f64; 3]] {
        &self.directions
    }

    /// Each entry's position (NaN where none was set, [`Self::set_positions`]).
    pub fn positions(&self) -> &[[f64; 3]] {
        &self.positions
    }

    /// Adds many landmarks, preparing them in parallel; returns their indices.
    pub fn extend(&mut self, landmarks: Vec<impl Into<Held>>) -> Result<Vec<usize>> {
        self.extend_on(landmarks, None)
    }

    /// [`Self::extend`] with the entries' patches in `spill` ([`Self::extend_views_on`]).
    pub fn extend_on(
        &mut self,
        landmarks: Vec<impl Into<Held>>,
        spill: Option<&Arc<Spill>>,
    ) -> Result<Vec<usize>> {
        let first = self.fresh_id();
        let ids = (first..first + landmarks.len() as u64).collect();
        self.extend_views_on(landmarks, ids, spill)
    }

    /// [`Self::extend`] with the physical boundary id of each landmark (see
    /// [`Self::add_view`]); `boundaries` must be as long as `landmarks`.
    pub fn extend_views(
        &mut self,
        landmarks: Vec<impl Into<Held>>,
        boundaries: Vec<u64>,
    ) -> Result<Vec<usize>> {
        self.extend_views_on(landmarks, boundaries, None)
    }

    /// [`Self::extend_views`] with each entry's patches moved into `spill` as soon as it is
    /// prepared ([`PreparedLandmark::set_aside`]): a re-inspection's survey database holds
    /// about 3 KB an entry instead of 22 (the results are the same bits).
    pub fn extend_views_on(
        &mut self,
        landmarks: Vec<impl Into<Held>>,
        boundaries: Vec<u64>,
        spill: Option<&Arc<Spill>>,
    ) -> Result<Vec<usize>> {
        let landmarks: Vec<Held> = landmarks.into_iter().map(Into::into).collect();
        if boundaries.len() != landmarks.len() {
            return Err(DecodError::invalid(
                "boundaries",
                format!("{} ids for {} landmarks", boundaries.len(), landmarks.len()),
            ));
        }
        if let (Some(first), Some(l)) = (self.entries.first(), landmarks.first()) {
            check_grids(&first.head, l.head())?;
        }
        for pair in landmarks.windows(2) {
            check_grids(pair[0].head(), pair[1].head())?;
        }
        // Those on disk are read back one at a time, as each is prepared.
        let prepared = landmarks
            .into_par_iter()
            .map(|l| {
                let mut view = PreparedLandmark::new(l, &self.config, &self.shape)?;
                if let Some(spill) = spill {
                    view.set_aside(spill)?;
                }
                Ok(Arc::new(view))
            })
            .collect::<Result<Vec<_>>>()?;
        self.store(prepared, boundaries)
    }

    /// [`Self::extend_views`] with landmarks already prepared under `cfg`
    /// ([`super::prepare_views`]); an error unless `cfg` is the database's own config (the
    /// entries would not compare like prepared ones). The entries share the views' data.
    pub fn extend_prepared(
        &mut self,
        prepared: Vec<Arc<PreparedLandmark>>,
        boundaries: Vec<u64>,
        cfg: &MatchingConfig,
    ) -> Result<Vec<usize>> {
        if *cfg != self.config {
            return Err(DecodError::invalid(
                "prepared",
                "views prepared under another matching config than the database's",
            ));
        }
        if boundaries.len() != prepared.len() {
            return Err(DecodError::invalid(
                "boundaries",
                format!("{} ids for {} landmarks", boundaries.len(), prepared.len()),
            ));
        }
        if let (Some(first), Some(p)) = (self.entries.first(), prepared.first()) {
            check_grids(&first.head, &p.head)?;
        }
        for pair in prepared.windows(2) {
            check_grids(&pair[0].head, &pair[1].head)?;
        }
        self.store(prepared, boundaries)
    }

    /// Appends prepared entries (grids checked) with their boundary ids.
    fn store(
        &mut self,
        prepared: Vec<Arc<PreparedLandmark>>,
        boundaries: Vec<u64>,
    ) -> Result<Vec<usize>> {
        let start = self.entries.len();
        for p in &prepared {
            self.coarse.push_first(&p.coarse);
        }
        self.entries.extend(prepared);
        self.positions.resize(self.entries.len(), [f64::NAN; 3]);
        self.directions.resize(self.entries.len(), [f64::NAN; 3]);
        self.distinct.extend(boundaries.iter().copied());
        self.boundaries.extend(boundaries);
        Ok((start..self.entries.len()).collect())
    }

    /// Best eligible candidate for `query` (rayon over candidates); see the module docs.
    pub fn query(&self, query: &Landmark, cfg: &MatchingConfig) -> Result<QueryResult> {
        self.query_with(query, cfg, true, Eligibility::WithinRun)
    }

    /// [`Self::query`] with the query's corridor axis in the frame of [`Self::set_directions`]
    /// (online mode within a run: the heading prior).
    pub fn query_directed(
        &self,
        query: &Landmark,
        direction: &[f64; 3],
        cfg: &MatchingConfig,
    ) -> Result<QueryResult> {
        if !direction.iter().all(|v| v.is_finite()) {
            return Err(DecodError::invalid(
                "direction",
                format!("{direction:?} is not finite"),
            ));
        }
        let ctx = QueryContext {
            direction: Some(*direction),
            parallel: true,
            eligibility: Eligibility::WithinRun,
        };
        self.query_in(Held::from(Arc::new(query.clone())), cfg, ctx)
    }

    /// [`Self::query`] on one thread (reference for the parallel path; results are identical).
    pub fn query_serial(&self, query: &Landmark, cfg: &MatchingConfig) -> Result<QueryResult> {
        self.query_with(query, cfg, false, Eligibility::WithinRun)
    }

    /// Batch mode (paper §IV-A): every query against the whole (outbound) database, queries
    /// in parallel.
    pub fn query_batch(
        &self,
        queries: &[Landmark],
        cfg: &MatchingConfig,
    ) -> Result<Vec<QueryResult>> {
        self.query_batch_with(queries, cfg, Eligibility::WithinRun)
    }

    /// [`Self::query_batch`] under an eligibility rule: [`Eligibility::CrossSession`] for a
    /// new run's boundaries against an earlier survey (every entry is a candidate; the same
    /// acceptance as within a run).
    pub fn query_batch_with(
        &self,
        queries: &[Landmark],
        cfg: &MatchingConfig,
        eligibility: Eligibility,
    ) -> Result<Vec<QueryResult>> {
        queries
            .par_iter()
            .map(|q| self.query_with(q, cfg, true, eligibility))
            .collect()
    }

    /// [`Self::query_batch_with`] on held landmarks: one on disk ([`crate::spill`]) is read
    /// back when its turn comes and let go once prepared, so the batch never holds the
    /// queries' cells all at once (a re-inspection's run against its survey).
    pub fn query_batch_held(
        &self,
        queries: &[Held],
        cfg: &MatchingConfig,
        eligibility: Eligibility,
    ) -> Result<Vec<QueryResult>> {
        let ctx = QueryContext {
            direction: None,
            parallel: true,
            eligibility,
        };
        queries
            .par_iter()
            .map(|q| self.query_in(q.clone(), cfg, ctx))
            .collect()
    }

    /// [`Self::query_batch_with`] for queries already prepared under `cfg`
    /// ([`super::prepare_views`]); under another config than the database's, each query is
    /// prepared again from its landmark (as [`Self::query_batch_with`] does).
    ///
    /// `directions`: each query's corridor axis in the frame of [`Self::set_directions`]
    /// (one per query), for the heading prior; `None` compares both headings everywhere.
    pub fn query_batch_prepared(
        &self,
        queries: &[&PreparedLandmark],
        directions: Option<&[[f64; 3]]>,
        cfg: &MatchingConfig,
        eligibility: Eligibility,
    ) -> Result<Vec<QueryResult>> {
        if let Some(d) = directions {
            if d.len() != queries.len() {
                return Err(DecodError::invalid(
                    "directions",
                    format!("{} directions for {} queries", d.len(), queries.len()),
                ));
            }
            if let Some((k, bad)) = d
                .iter()
                .enumerate()
                .find(|(_, v)| !v.iter().all(|x| x.is_finite()))
            {
                return Err(DecodError::invalid(
                    "directions",
                    format!("query {k}: direction {bad:?} is not finite"),
                ));
            }
        }
        let context = |k: usize| QueryContext {
            direction: directions.and_then(|d| d.get(k)).copied(),
            parallel: true,
            eligibility,
        };
        if *cfg != self.config {
            return queries
                .par_iter()
                .enumerate()
                .map(|(k, q)| self.query_in(q.source.clone(), cfg, context(k)))
                .collect();
        }
        if let (Some(first), Some(q)) = (self.entries.first(), queries.first()) {
            check_grids(&first.head, &q.head)?;
        }
        for pair in queries.windows(2) {
            check_grids(&pair[0].head, &pair[1].head)?;
        }
        queries
            .par_iter()
            .enumerate()
            .map(|(k, q)| self.query_prepared(q, &self.entries, &self.shape, cfg, context(k)))
            .collect()
    }

    /// Online mode: query against every landmark already in the database (all older ones),
    /// then add it. Returns the query result and the new landmark's index.
    pub fn query_online(
        &mut self,
        landmark: Landmark,
        cfg: &MatchingConfig,
    ) -> Result<(QueryResult, usize)> {
        let result = self.query_with(&landmark, cfg, true, Eligibility::WithinRun)?;
        let index = self.add(landmark)?;
        Ok((result, index))
    }

    /// Bytes held per landmark: the mean over the entries of the prepared data
    /// ([`PreparedLandmark::heap_bytes`]) plus the contiguous coarse signature and the
    /// boundary id.
    pub fn bytes_per_landmark(&self) -> usize {
        if self.entries.is_empty() {
            return 0;
        }
        let prepared: usize = self.entries.iter().map(|e| e.heap_bytes()).sum();
        prepared / self.entries.len()
            + self.coarse.bytes_per_landmark()
            + std::mem::size_of::<PreparedLandmark>()
            + std::mem::size_of::<u64>()
    }

    /// The indices the exact matcher compares `q` with: every eligible entry, or under
    /// `retrieval = "coarse"` with more than `retrieval_min_candidates` eligible, the coarse
    /// short list ([`super::retrieval`]). Also returns the eligible indices.
    fn candidates(
        &self,
        q: &PreparedLandmark,
        entries: &[Arc<PreparedLandmark>],
        cfg: &MatchingConfig,
        parallel: bool,
        eligibility: Eligibility,
    ) -> (Vec<usize>, Vec<usize>) {
        let ok = |(i, c): (usize, &Arc<PreparedLandmark>)| {
            match eligibility {
                Eligibility::WithinRun => eligible_prepared(q, c, cfg),
                Eligibility::CrossSession => true,
                Eligibility::AcrossPasses => !shares_scans(q, c),
            }
            .then_some(i)
        };
        let eligible: Vec<usize> = if parallel {
            entries.par_iter().enumerate().filter_map(ok).collect()
        } else {
            entries.iter().enumerate().filter_map(ok).collect()
        };
        let coarse = cfg.retrieval == "coarse"
            && eligible.len() > cfg.retrieval_min_candidates.max(cfg.retrieval_short_list);
        if !coarse {
            return (eligible.clone(), eligible);
        }
        let short = if std::ptr::eq(entries, self.entries.as_slice()) {
            self.coarse
                .short_list(&q.coarse, &eligible, cfg.retrieval_short_list, parallel)
        } else {
            let mut index = CoarseIndex::default();
            entries.iter().for_each(|e| index.push_first(&e.coarse));
            index.short_list(&q.coarse, &eligible, cfg.retrieval_short_list, parallel)
        };
        (short, eligible)
    }

    /// The eligible entries not yet compared, of other boundaries than `best`'s (its own
    /// other views are never its runner-up), whose boundary lies within
    /// `retrieval_neighbour_extents` descriptor extents (rows x cell length) of entry
    /// `best`'s. Why: where boundaries repeat closer than a descriptor's extent (tunnel rings,
    /// steel arches) neighbouring boundaries share most of the unwrapped wall, so the one
    /// that competes with the best is its neighbour, and the pooled signature ranks it low.
    /// Measured on simulated re-inspections before this widening: the coarse stage accepted
    /// 68 queries where the exhaustive matcher accepted 33 in the shield tunnel, 614 against
    /// 377 among arches, nearly all the extra ones exhaustive `not_unique`. Empty when `best`
    /// has no position.
    fn neighbours_of(
        &self,
        best: usize,
        eligible: &[usize],
        compared: &[bool],
        cfg: &MatchingConfig,
    ) -> Vec<usize> {
        let placement = self.placement();
        let placed = |i: usize| placement.position(i);
        let (Some(centre), Some(entry)) = (placed(best), self.entries.get(best)) else {
            return Vec::new();
        };
        let d = &entry.head.descriptor;
        let radius = cfg.retrieval_neighbour_extents * d.rows as f64 * d.cell_z_m;
        let boundary = self.boundaries.get(best);
        eligible
            .iter()
            .copied()
            .filter(|&i| {
                !compared.get(i).copied().unwrap_or(true)
                    && self.boundaries.get(i) != boundary
                    && placed(i).is_some_and(|p| distance2(centre, p) <= radius * radius)
            })
            .collect()
    }

    /// The query under an eligibility rule.
    fn query_with(
        &self,
        query: &Landmark,
        cfg: &MatchingConfig,
        parallel: bool,
        eligibility: Eligibility,
    ) -> Result<QueryResult> {
        let ctx = QueryContext {
            direction: None,
            parallel,
            eligibility,
        };
        self.query_in(Held::from(Arc::new(query.clone())), cfg, ctx)
    }

    /// The query in a context (with its direction, in parallel or not, eligibility).
    fn query_in(
        &self,
        query: Held,
        cfg: &MatchingConfig,
        ctx: QueryContext,
    ) -> Result<QueryResult> {
        if let Some(first) = self.entries.first() {
            check_grids(&first.head, query.head())?;
        }
        // Entries prepared with another config are re-prepared (correct, slower).
        let reprepared;
        let (entries, shape): (&[Arc<PreparedLandmark>], PatchShape) =
            if same_preparation(&self.config, cfg) {
                (&self.entries, self.shape.clone())
            } else {
                let shape = PatchShape::new(cfg);
                reprepared = self
                    .entries
                    .iter()
                    .map(|e| PreparedLandmark::new(e.source.clone(), cfg, &shape).map(Arc::new))
                    .collect::<Result<Vec<_>>>()?;
                (&reprepared, shape)
            };
        let q = PreparedLandmark::new_query(query, cfg, &shape)?;
        self.query_prepared(&q, entries, &shape, cfg, ctx)
    }

    /// The query, prepared like `entries` (with all its coarse signatures), against them.
    fn query_prepared(
        &self,
        q: &PreparedLandmark,
        entries: &[Arc<PreparedLandmark>],
        shape: &PatchShape,
        cfg: &MatchingConfig,
        ctx: QueryContext,
    ) -> Result<QueryResult> {
        let QueryContext {
            direction,
            parallel,
            eligibility,
        } = ctx;
        let side = QuerySide::new(q)?;
        let (compared, eligible) = self.candidates(q, entries, cfg, parallel, eligibility);
        let headings = |index: usize| match (direction, self.directions.get(index)) {
            (Some(d), Some(e)) if cfg.heading_from_odometry => heading::prior(&d, e),
            _ => &Heading::BOTH,
        };
        let work = |&index: &usize| {
            compare_prepared_in(q, &side, &entries[index], headings(index), cfg, shape)
                .map(|pair| (index, pair))
        };
        let run = |indices: &[usize]| -> Result<Vec<(usize, PairResult)>> {
            if parallel {
                indices.par_iter().map(work).collect()
            } else {
                indices.iter().map(work).collect()
            }
        };
        let mut pairs = run(&compared)?;
        if compared.len() < eligible.len() {
            // A short list: widen it around the best until the best stays (a neighbour may
            // beat it, and then its own neighbours are the competitors).
            let mut seen = vec![false; entries.len()];
            compared.iter().for_each(|&i| seen[i] = true);
            let mut widened_around = Vec::new();
            while let Some(best) = best_pair(&pairs).map(|b| b.0) {
                if widened_around.contains(&best) {
                    break;
                }
                widened_around.push(best);
                let extra = self.neighbours_of(best, &eligible, &seen, cfg);
                extra.iter().for_each(|&i| seen[i] = true);
                pairs.extend(run(&extra)?);
            }
        }
        let family = if eligible.len() == self.boundaries.len() {
            self.distinct.len()
        } else {
            distinct_boundaries(&self.boundaries, &eligible)
        };
        let placed = self.placement();
        let mut result = decide(q, entries, &self.boundaries, placed, &pairs, family, cfg);
        result.eligible = eligible.len();
        if eligible.is_empty() && !entries.is_empty() {
            result.rejection = Some(Rejection::Ineligible);
        }
        Ok(result)
    }
}

/// Whether `a` ranks above `b` (or `b` is none): higher score, then more inliers, then the
/// lower index.
fn ranks_above(a: &(usize, PairResult), b: Option<&(usize, PairResult)>) -> bool {
    let rank = |p: &PairResult| (p.score, p.inliers);
    b.is_none_or(|o| rank(&a.1) > rank(&o.1) || (rank(&a.1) == rank(&o.1) && a.0 < o.0))
}

/// The best-ranked pair ([`ranks_above`]).
fn best_pair(pairs: &[(usize, PairResult)]) -> Option<&(usize, PairResult)> {
    let mut best = None;
    for item in pairs {
        if ranks_above(item, best) {
            best = Some(item);
        }
    }
    best
}

fn distance2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// Number of distinct physical boundaries among `indices` (the null model's family: every
/// eligible boundary, whether or not the coarse stage handed it to the exact matcher).
fn distinct_boundaries(boundaries: &[u64], indices: &[usize]) -> usize {
    let mut ids: Vec<u64> = indices
        .iter()
        .map(|&i| boundaries.get(i).copied().unwrap_or(u64::MAX - i as u64))
        .collect();
    ids.sort_unstable();
    ids.dedup();
    ids.len()
}

/// The inlier margin beyond the counting noise of best and runner-up
/// (`MatchingConfig::uniqueness_sigma`).
fn count_margin(pair: &PairResult, result: &QueryResult, cfg: &MatchingConfig) -> bool {
    let (k_best, k_second) = (pair.inliers as f64, result.runner_up_inliers as f64);
    k_best - k_second >= cfg.uniqueness_sigma * (k_best + k_second).sqrt()
}

/// The paper-mode uniqueness test: a score ratio over the runner-up, and the count margin.
fn is_unique(pair: &PairResult, result: &QueryResult, cfg: &MatchingConfig) -> bool {
    pair.score >= cfg.uniqueness_ratio * result.runner_up_score && count_margin(pair, result, cfg)
}

/// Family-wise chance of `pair` against `n` candidates (`null_model` module docs).
fn chance_of(
    q: &PreparedLandmark,
    c: &PreparedLandmark,
    pair: &PairResult,
    n: usize,
    cfg: &MatchingConfig,
) -> f64 {
    null_model::family_wise(super::pair_chance(q, c, pair, cfg), n)
}

/// The rejection of the best pair under the configured acceptance rule, if any.
fn judge(pair: &PairResult, result: &QueryResult, cfg: &MatchingConfig) -> Option<Rejection> {
    if let Some(r) = pair.rejection {
        return Some(r);
    }
    if pair.score <= 0.0 {
        return Some(Rejection::TooFewInliers);
    }
    if !cfg.verification {
        return None;
    }
    if cfg.acceptance == "null_model" {
        if result.chance > cfg.false_alarm_rate {
            Some(Rejection::Chance)
        } else if result.runner_up_chance <= cfg.uniqueness_alpha
            && null_model::as_likely(pair.inliers, result.runner_up_inliers) > cfg.uniqueness_alpha
        {
            Some(Rejection::NotUnique)
        } else {
            None
        }
    } else if !is_unique(pair, result, cfg) {
        Some(Rejection::NotUnique)
    } else {
        None
    }
}

/// The database's entry positions and directions ([`LandmarkDatabase::set_positions`],
/// [`LandmarkDatabase::set_directions`]; NaN where unset).
#[derive(Clone, Copy)]
struct Placement<'a> {
    positions: &'a [[f64; 3]],
    directions: &'a [[f64; 3]],
}

impl Placement<'_> {
    /// Entry `index`'s position, if it was placed (set rows are finite, unset ones NaN:
    /// `check_rows`).
    fn position(&self, index: usize) -> Option<&[f64; 3]> {
        self.positions.get(index).filter(|p| p[0].is_finite())
    }

    /// Where `pair` with entry `index` puts the query's boundary, in the database's frame:
    /// the entry's position moved by the pair's axial offset along the entry's direction
    /// under the pair's heading (`selection.effective_db_origin` in the Python package does
    /// the same in the entry's submap frame). None for an unplaced or unoriented entry (a
    /// set direction is finite and non-zero: [`LandmarkDatabase::set_directions`]).
    fn implied(&self, index: usize, pair: &PairResult) -> Option<[f64; 3]> {
        let p = self.position(index)?;
        let d = self.directions.get(index).filter(|d| d[0].is_finite())?;
        let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sign = match pair.heading {
            Heading::Forward => 1.0,
            Heading::Reversed => -1.0,
        };
        let shift = pair.dz_m * sign / norm;
        Some([
            p[0] + shift * d[0],
            p[1] + shift * d[1],
            p[2] + shift * d[2],
        ])
    }
}

/// The runner-up of `best` among `pairs`: the best other candidate that is neither a view of
/// the same boundary, nor within `runner_up_exclusion_s` of it, nor the same place
/// (`runner_up_same_place_rows`).
fn runner_up<'p>(
    best: Option<&(usize, PairResult)>,
    pairs: &'p [(usize, PairResult)],
    entries: &[Arc<PreparedLandmark>],
    boundaries: &[u64],
    placed: Placement<'_>,
    cfg: &MatchingConfig,
) -> Option<&'p (usize, PairResult)> {
    let best_stamp = best.map(|b| entries[b.0].head.submap_stamp);
    let boundary = |i: usize| boundaries.get(i).copied().unwrap_or(u64::MAX - i as u64);
    let same_place = best.and_then(|(i, p)| {
        let radius = cfg.runner_up_same_place_rows * entries[*i].head.descriptor.cell_z_m;
        (radius > 0.0)
            .then(|| placed.implied(*i, p))
            .flatten()
            .map(|at| (at, radius))
    });
    let mut second: Option<&(usize, PairResult)> = None;
    for item in pairs {
        let same = best.is_some_and(|b| boundary(b.0) == boundary(item.0));
        let excluded = best_stamp.is_some_and(|t| {
            (entries[item.0].head.submap_stamp - t).abs() < cfg.runner_up_exclusion_s
        });
        let merged = same_place.is_some_and(|(at, radius)| {
            placed
                .implied(item.0, &item.1)
                .is_some_and(|here| distance2(&at, &here) <= radius * radius)
        });
        if !same && !excluded && !merged && ranks_above(item, second) {
            second = Some(item);
        }
    }
    second
}

/// Ranks the candidates and applies the acceptance rule (module docs).
fn decide(
    q: &PreparedLandmark,
    entries: &[Arc<PreparedLandmark>],
    boundaries: &[u64],
    placed: Placement<'_>,
    pairs: &[(usize, PairResult)],
    family: usize,
    cfg: &MatchingConfig,
) -> QueryResult {
    let query = &*q.head;
    let best = best_pair(pairs);
    let second = runner_up(best, pairs, entries, boundaries, placed, cfg);
    let mut result = QueryResult {
        query_stamp: query.submap_stamp,
        query_origin_in_submap: query.origin_in_submap,
        query_axis_in_submap: query.axis_in_submap,
        candidate_index: None,
        candidate_stamp: f64::NAN,
        candidate_origin_in_submap: [0.0; 3],
        candidate_axis_in_submap: [0.0; 3],
        pair: None,
        accepted: false,
        rejection: Some(Rejection::NoCandidates),
        runner_up_score: second.map_or(0.0, |s| s.1.score),
        runner_up_inliers: second.map_or(0, |s| s.1.inliers),
        runner_up_index: second.map(|s| s.0),
        eligible: pairs.len(),
        chance: 1.0,
        runner_up_chance: 1.0,
    };
    let Some((index, pair)) = best else {
        if !entries.is_empty() {
            result.rejection = Some(Rejection::Ineligible);
        }
        return result;
    };
    let c = &entries[*index].head;
    result.candidate_index = Some(*index);
    result.candidate_stamp = c.submap_stamp;
    result.candidate_origin_in_submap = c.origin_in_submap;
    result.candidate_axis_in_submap = c.axis_in_submap;
    result.pair = Some(pair.clone());
    if cfg.verification {
        let n = family;
        result.chance = chance_of(q, &entries[*index], pair, n, cfg);
        if let Some((k, p)) = second {
            result.runner_up_chance = chance_of(q, &entries[*k], p, n, cfg);
        }
    }
    result.rejection = judge(pair, &result, cfg);
    result.accepted = result.rejection.is_none();
    result
}

impl LandmarkDatabase {
    /// Writes the database (landmarks and config) as versioned JSON.
    pub fn save(&self, path: &Path) -> Result<()> {
        let saved = SavedDatabase {
            format: FORMAT_NAME.into(),
            version: FORMAT_VERSION,
            config: Some(self.config.clone()),
            landmarks: self
                .entries
                .iter()
                .map(|e| e.source.landmark().map(|l| (*l).clone()))
                .collect::<Result<_>>()?,
            boundaries: Some(self.boundaries.clone()),
            positions: Some(
                self.positions
                    .iter()
                    .map(|p| p[0].is_finite().then_some(*p))
                    .collect(),
            ),
        };
        let file = std::fs::File::create(path).map_err(|source| DecodError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        serde_json::to_writer(std::io::BufWriter::new(file), &saved).map_err(|e| {
            DecodError::Database {
                path: path.to_path_buf(),
                reason: format!("cannot write: {e}"),
            }
        })
    }

    /// Reads a database written by [`Self::save`]; its entries are prepared with `config`
    /// (or, if `None`, with the config it was saved with).
    pub fn load(path: &Path, config: Option<&MatchingConfig>) -> Result<Self> {
        let db_err = |reason: String| DecodError::Database {
            path: path.to_path_buf(),
            reason,
        };
        let file = std::fs::File::open(path).map_err(|source| DecodError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let value: serde_json::Value = serde_json::from_reader(std::io::BufReader::new(file))
            .map_err(|e| db_err(format!("not a decod landmark database (invalid JSON: {e})")))?;
        let format = value.get("format").and_then(|f| f.as_str()).unwrap_or("");
        if format != FORMAT_NAME {
            return Err(db_err(format!(
                "not a decod landmark database (format {format:?}, expected {FORMAT_NAME:?})"
            )));
        }
        let version = value.get("version").and_then(|v| v.as_u64());
        if version != Some(u64::from(FORMAT_VERSION)) {
            return Err(db_err(format!(
                "format version {} is not supported (this build reads version {FORMAT_VERSION})",
                version.map_or("<missing>".to_string(), |v| v.to_string())
            )));
        }
        let saved: SavedDatabase =
            serde_json::from_value(value).map_err(|e| db_err(format!("corrupt database: {e}")))?;
        let config = match (config, saved.config) {
            (Some(c), _) => c.clone(),
            (None, Some(c)) => c,
            (None, None) => return Err(db_err("no config saved and none given".into())),
        };
        let mut db = Self::new(&config);
        let ids = saved
            .boundaries
            .unwrap_or_else(|| (0..saved.landmarks.len() as u64).collect());
        let n = saved.landmarks.len();
        db.extend_views(saved.landmarks, ids)
            .map_err(|e| db_err(format!("invalid landmark: {e}")))?;
        if let Some(positions) = saved.positions {
            if positions.len() != n {
                return Err(db_err(format!(
                    "{} positions for {n} landmarks",
                    positions.len()
                )));
            }
            let (indices, placed): (Vec<usize>, Vec<[f64; 3]>) = positions
                .into_iter()
                .enumerate()
                .filter_map(|(i, p)| p.map(|p| (i, p)))
                .unzip();
            db.set_positions(&indices, &placed)
                .map_err(|e| db_err(format!("invalid position: {e}")))?;
        }
        Ok(db)
    }
}
