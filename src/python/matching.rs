//! Bindings for the matching layer: `compare`, `LandmarkDatabase`, the typed results, and
//! the synthetic descriptor generator (for tests and examples). Configs cross as JSON of the
//! `[matching]` section (the Python side resolves presets and TOML files). Heavy calls release
//! the GIL through [`detached`].

use std::path::PathBuf;
use std::sync::Arc;

use numpy::{PyArray1, PyArray2, PyReadonlyArray2};
use pyo3::prelude::*;

use super::arrays::{flat_to_numpy, points_n3, rows_to_numpy};
use super::detached;
use super::errors::to_py_err;
use super::landmark::{PyLandmark, PySpill, held_of};
use crate::config::MatchingConfig;
use crate::error::DecodError;
use crate::matching::Heading;
use crate::matching::database::Eligibility;
use crate::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};
use crate::matching::{self, LandmarkDatabase, PairResult, QueryResult};

/// The eligibility rule of a batch query: against an earlier survey, between the passes of
/// the run, or within the run.
fn eligibility_of(cross_session: bool, across_passes: bool) -> Eligibility {
    if cross_session {
        Eligibility::CrossSession
    } else if across_passes {
        Eligibility::AcrossPasses
    } else {
        Eligibility::WithinRun
    }
}

fn config_from_json(text: &str) -> PyResult<MatchingConfig> {
    let cfg: MatchingConfig = serde_json::from_str(text)
        .map_err(|e| to_py_err(DecodError::config("matching", e.to_string())))?;
    let mut whole = crate::config::DecodConfig::tunnel();
    whole.matching = cfg.clone();
    whole.validate().map_err(to_py_err)?;
    Ok(cfg)
}

/// One query/candidate comparison (see `decod::matching::PairResult`).
#[pyclass(name = "PairResult", module = "decod_rs._core", frozen)]
pub(crate) struct PyPairResult {
    inner: PairResult,
}

#[pymethods]
impl PyPairResult {
    /// Relative heading of the better hypothesis, degrees (0 or 180).
    #[getter]
    fn heading_deg(&self) -> f64 {
        self.inner.heading.degrees()
    }
    /// Fraction of cells observed in both descriptors under that heading.
    #[getter]
    fn overlap_fraction(&self) -> f64 {
        self.inner.overlap_fraction
    }
    /// Keypoints of the query, N_i.
    #[getter]
    fn query_keypoints(&self) -> usize {
        self.inner.query_keypoints
    }
    /// Keypoints of the candidate, N_j.
    #[getter]
    fn candidate_keypoints(&self) -> usize {
        self.inner.candidate_keypoints
    }
    /// Unique mutual nearest-neighbour correspondences.
    #[getter]
    fn matches(&self) -> usize {
        self.inner.matches
    }
    /// Verified inliers K.
    #[getter]
    fn inliers(&self) -> usize {
        self.inner.inliers
    }
    /// S = 2K / (N_i + N_j).
    #[getter]
    fn score(&self) -> f64 {
        self.inner.score
    }
    /// Axial offset, metres (query feature at z lies at z + dz_m in the candidate).
    #[getter]
    fn dz_m(&self) -> f64 {
        self.inner.dz_m
    }
    /// Circumferential offset, fraction of the circumference in [-0.5, 0.5).
    #[getter]
    fn dp(&self) -> f64 {
        self.inner.dp
    }
    /// Chance that unrelated surfaces verify this well (null model; 1 if not computed).
    #[getter]
    fn chance(&self) -> f64 {
        self.inner.chance
    }
    /// Why the pair is rejected on its own (`insufficient_overlap`, `too_few_inliers`), or None.
    #[getter]
    fn rejection(&self) -> Option<&'static str> {
        self.inner.rejection.map(|r| r.as_str())
    }
    fn __repr__(&self) -> String {
        let r = &self.inner;
        format!(
            "PairResult(heading={}, K={}, S={:.3}, dz_m={:.3}, dp={:.4}, overlap={:.2}, rejection={:?})",
            r.heading.degrees(),
            r.inliers,
            r.score,
            r.dz_m,
            r.dp,
            r.overlap_fraction,
            r.rejection.map(|x| x.as_str())
        )
    }
}

/// The outcome of one query (see `decod::matching::QueryResult`).
#[pyclass(name = "QueryResult", module = "decod_rs._core", frozen)]
pub(crate) struct PyQueryResult {
    inner: QueryResult,
}

#[pymethods]
impl PyQueryResult {
    /// Query submap stamp, seconds.
    #[getter]
    fn query_stamp(&self) -> f64 {
        self.inner.query_stamp
    }
    /// Query origin in its submap frame, `(3,)` metres.
    #[getter]
    fn query_origin<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.query_origin_in_submap)
    }
    /// Query axis in its submap frame, `(3,)`.
    #[getter]
    fn query_axis<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.query_axis_in_submap)
    }
    /// Database index of the best candidate, or None.
    #[getter]
    fn candidate_index(&self) -> Option<usize> {
        self.inner.candidate_index
    }
    /// Best candidate's submap stamp (NaN if none).
    #[getter]
    fn candidate_stamp(&self) -> f64 {
        self.inner.candidate_stamp
    }
    /// Best candidate's origin in its submap frame, `(3,)` metres.
    #[getter]
    fn candidate_origin<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.candidate_origin_in_submap)
    }
    /// Best candidate's axis in its submap frame, `(3,)`.
    #[getter]
    fn candidate_axis<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.inner.candidate_axis_in_submap)
    }
    /// The best pair, or None without eligible candidates.
    #[getter]
    fn pair(&self) -> Option<PyPairResult> {
        self.inner.pair.clone().map(|inner| PyPairResult { inner })
    }
    /// Relative heading, degrees (0 or 180).
    #[getter]
    fn heading_deg(&self) -> f64 {
        self.inner.heading().degrees()
    }
    /// Inliers K of the best pair (0 if none).
    #[getter]
    fn inliers(&self) -> usize {
        self.inner.pair.as_ref().map_or(0, |p| p.inliers)
    }
    /// Score S of the best pair (0 if none).
    #[getter]
    fn score(&self) -> f64 {
        self.inner.pair.as_ref().map_or(0.0, |p| p.score)
    }
    /// Axial offset of the best pair, metres.
    #[getter]
    fn dz_m(&self) -> f64 {
        self.inner.pair.as_ref().map_or(0.0, |p| p.dz_m)
    }
    /// Circumferential offset of the best pair, fraction of the circumference.
    #[getter]
    fn dp(&self) -> f64 {
        self.inner.pair.as_ref().map_or(0.0, |p| p.dp)
    }
    /// Accepted as a loop closure.
    #[getter]
    fn accepted(&self) -> bool {
        self.inner.accepted
    }
    /// Why not accepted (`ineligible`, `no_candidates`, `insufficient_overlap`,
    /// `too_few_inliers`, `chance`, `not_unique`), or None.
    #[getter]
    fn rejection(&self) -> Option<&'static str> {
        self.inner.rejection.map(|r| r.as_str())
    }
    /// Best score among the other eligible candidates (uniqueness reference).
    #[getter]
    fn runner_up_score(&self) -> f64 {
        self.inner.runner_up_score
    }
    /// Inliers of the runner-up.
    #[getter]
    fn runner_up_inliers(&self) -> usize {
        self.inner.runner_up_inliers
    }
    /// Database index of the runner-up, or None.
    #[getter]
    fn runner_up_index(&self) -> Option<usize> {
        self.inner.runner_up_index
    }
    /// Number of eligible candidates compared.
    #[getter]
    fn eligible(&self) -> usize {
        self.inner.eligible
    }
    /// Family-wise chance that the best candidate's inliers are chance agreement (null
    /// model; 1 when not computed).
    #[getter]
    fn chance(&self) -> f64 {
        self.inner.chance
    }
    /// The same for the runner-up (1 when there is none).
    #[getter]
    fn runner_up_chance(&self) -> f64 {
        self.inner.runner_up_chance
    }
    /// The result as JSON.
    fn to_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.inner)
            .map_err(|e| to_py_err(DecodError::invalid("QueryResult", e.to_string())))
    }
    fn __repr__(&self) -> String {
        let r = &self.inner;
        format!(
            "QueryResult(query_stamp={:.3}, candidate={:?}, accepted={}, K={}, S={:.3}, runner_up_S={:.3}, rejection={:?})",
            r.query_stamp,
            r.candidate_index,
            r.accepted,
            self.inliers(),
            self.score(),
            r.runner_up_score,
            r.rejection.map(|x| x.as_str())
        )
    }
}

/// Compares two landmarks under both headings (GIL released).
#[pyfunction]
fn compare(
    py: Python<'_>,
    query: PyRef<'_, PyLandmark>,
    candidate: PyRef<'_, PyLandmark>,
    config_json: &str,
) -> PyResult<PyPairResult> {
    let cfg = config_from_json(config_json)?;
    let (q, c) = (query.whole()?, candidate.whole()?);
    let inner = detached(py, move || matching::compare(&q, &c, &cfg))?;
    Ok(PyPairResult { inner })
}

/// Many comparisons among `landmarks` (each prepared once), pairs in parallel, GIL released;
/// `same_heading`: under 0 degrees only (views of one pass).
#[pyfunction]
#[pyo3(signature = (landmarks, pairs, config_json, same_heading = false))]
fn compare_pairs(
    py: Python<'_>,
    landmarks: Vec<PyRef<'_, PyLandmark>>,
    pairs: Vec<(usize, usize)>,
    config_json: &str,
    same_heading: bool,
) -> PyResult<Vec<PyPairResult>> {
    let cfg = config_from_json(config_json)?;
    let ls = held_of(&landmarks);
    let results = detached(py, move || {
        matching::compare_pairs(&ls, &pairs, &cfg, same_heading)
    })?;
    Ok(results
        .into_iter()
        .map(|inner| PyPairResult { inner })
        .collect())
}

/// A run's landmarks prepared once for the matcher (see `decod::matching::prepare_views`):
/// the within-pass comparisons, the database entries and the queries share them.
#[pyclass(name = "PreparedViews", module = "decod_rs._core", frozen)]
pub(crate) struct PyPreparedViews {
    views: Vec<Arc<matching::PreparedLandmark>>,
    config: MatchingConfig,
}

#[pymethods]
impl PyPreparedViews {
    /// `spill`: where each view's patches wait while the passes are matched (None: memory).
    #[new]
    #[pyo3(signature = (landmarks, config_json, spill = None))]
    fn py_new(
        py: Python<'_>,
        landmarks: Vec<PyRef<'_, PyLandmark>>,
        config_json: &str,
        spill: Option<PyRef<'_, PySpill>>,
    ) -> PyResult<Self> {
        let config = config_from_json(config_json)?;
        let ls = held_of(&landmarks);
        let cfg = config.clone();
        let spill = spill.map(|s| Arc::clone(&s.inner));
        let views = detached(py, move || {
            matching::prepare_views(&ls, &cfg, spill.as_ref())
        })?;
        Ok(Self { views, config })
    }
    fn __len__(&self) -> usize {
        self.views.len()
    }
    /// `compare_pairs` on the prepared views (indices into the landmarks given).
    #[pyo3(signature = (pairs, same_heading = false))]
    fn compare_pairs(
        &self,
        py: Python<'_>,
        pairs: Vec<(usize, usize)>,
        same_heading: bool,
    ) -> PyResult<Vec<PyPairResult>> {
        let (views, cfg) = (&self.views, &self.config);
        let results = detached(py, move || {
            matching::compare_view_pairs(views, &pairs, cfg, same_heading)
        })?;
        Ok(results
            .into_iter()
            .map(|inner| PyPairResult { inner })
            .collect())
    }
}

impl PyPreparedViews {
    /// The views at `indices`, or an error naming the first index out of range.
    fn pick(&self, indices: &[usize]) -> PyResult<Vec<&Arc<matching::PreparedLandmark>>> {
        indices
            .iter()
            .map(|&i| {
                self.views.get(i).ok_or_else(|| {
                    to_py_err(DecodError::invalid(
                        "indices",
                        format!("{i} out of range for {} views", self.views.len()),
                    ))
                })
            })
            .collect()
    }
}

/// A landmark database (see `decod::matching::LandmarkDatabase`).
#[pyclass(name = "LandmarkDatabase", module = "decod_rs._core")]
pub(crate) struct PyLandmarkDatabase {
    inner: LandmarkDatabase,
}

#[pymethods]
impl PyLandmarkDatabase {
    #[new]
    fn py_new(config_json: &str) -> PyResult<Self> {
        Ok(Self {
            inner: LandmarkDatabase::new(&config_from_json(config_json)?),
        })
    }
    /// Prepares and stores a landmark; returns its index.
    fn add(&mut self, py: Python<'_>, landmark: PyRef<'_, PyLandmark>) -> PyResult<usize> {
        let l = (*landmark.whole()?).clone();
        let db = &mut self.inner;
        detached(py, move || db.add(l))
    }
    /// Stores one view of physical boundary `boundary`; returns its index.
    fn add_view(
        &mut self,
        py: Python<'_>,
        landmark: PyRef<'_, PyLandmark>,
        boundary: u64,
    ) -> PyResult<usize> {
        let l = (*landmark.whole()?).clone();
        let db = &mut self.inner;
        detached(py, move || db.add_view(l, boundary))
    }
    /// Prepares (in parallel) and stores views with their physical boundary ids; `spill`:
    /// where the entries' patches wait (None: memory).
    #[pyo3(signature = (landmarks, boundaries, spill = None))]
    fn extend_views(
        &mut self,
        py: Python<'_>,
        landmarks: Vec<PyRef<'_, PyLandmark>>,
        boundaries: Vec<u64>,
        spill: Option<PyRef<'_, PySpill>>,
    ) -> PyResult<Vec<usize>> {
        let ls = held_of(&landmarks);
        let spill = spill.map(|s| Arc::clone(&s.inner));
        let db = &mut self.inner;
        detached(py, move || {
            db.extend_views_on(ls, boundaries, spill.as_ref())
        })
    }
    /// Stores the views at `indices` of `views` (prepared under this database's config),
    /// each under its physical boundary id; returns their indices.
    fn extend_prepared(
        &mut self,
        py: Python<'_>,
        views: PyRef<'_, PyPreparedViews>,
        indices: Vec<usize>,
        boundaries: Vec<u64>,
    ) -> PyResult<Vec<usize>> {
        let picked: Vec<Arc<matching::PreparedLandmark>> =
            views.pick(&indices)?.into_iter().cloned().collect();
        let cfg = views.config.clone();
        let db = &mut self.inner;
        detached(py, move || db.extend_prepared(picked, boundaries, &cfg))
    }
    /// Batch queries with the views at `indices` of `views` (see `query_batch`);
    /// `across_passes`: the queries are another pass of the run than the database's (no
    /// time separation, `Eligibility::AcrossPasses`); `directions` (k, 3): each query's
    /// corridor axis in the frame of `set_directions` (the heading prior).
    #[pyo3(signature = (views, indices, cross_session, across_passes = false, directions = None))]
    fn query_batch_prepared(
        &self,
        py: Python<'_>,
        views: PyRef<'_, PyPreparedViews>,
        indices: Vec<usize>,
        cross_session: bool,
        across_passes: bool,
        directions: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<Vec<PyQueryResult>> {
        let picked: Vec<&matching::PreparedLandmark> =
            views.pick(&indices)?.into_iter().map(|v| &**v).collect();
        let directions = directions
            .map(|d| points_n3(&d, "directions"))
            .transpose()?;
        let cfg = &views.config;
        let db = &self.inner;
        let eligibility = eligibility_of(cross_session, across_passes);
        let results = detached(py, move || {
            db.query_batch_prepared(&picked, directions.as_deref(), cfg, eligibility)
        })?;
        Ok(results
            .into_iter()
            .map(|inner| PyQueryResult { inner })
            .collect())
    }
    /// The physical boundary id of every entry.
    fn boundaries(&self) -> Vec<u64> {
        self.inner.boundaries().to_vec()
    }
    /// Places entries `indices` at `positions` (k, 3) in the database's frame.
    fn set_positions(
        &mut self,
        indices: Vec<usize>,
        positions: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let rows = points_n3(&positions, "positions")?;
        self.inner.set_positions(&indices, &rows).map_err(to_py_err)
    }
    /// Orients entries `indices` along `directions` (k, 3) in the positions' frame.
    fn set_directions(
        &mut self,
        indices: Vec<usize>,
        directions: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let rows = points_n3(&directions, "directions")?;
        self.inner
            .set_directions(&indices, &rows)
            .map_err(to_py_err)
    }
    /// Each entry's direction (n, 3), NaN where none was set.
    fn directions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        rows_to_numpy(py, self.inner.directions())
    }
    /// Each entry's position (n, 3), NaN where none was set.
    fn positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        rows_to_numpy(py, self.inner.positions())
    }
    /// Prepares (in parallel) and stores landmarks; returns their indices. `spill`: where
    /// the entries' patches wait (None: memory).
    #[pyo3(signature = (landmarks, spill = None))]
    fn extend(
        &mut self,
        py: Python<'_>,
        landmarks: Vec<PyRef<'_, PyLandmark>>,
        spill: Option<PyRef<'_, PySpill>>,
    ) -> PyResult<Vec<usize>> {
        let ls = held_of(&landmarks);
        let spill = spill.map(|s| Arc::clone(&s.inner));
        let db = &mut self.inner;
        detached(py, move || db.extend_on(ls, spill.as_ref()))
    }
    /// Best eligible candidate for `query`; `direction` (3,): its corridor axis in the frame
    /// of `set_directions` (the heading prior).
    #[pyo3(signature = (query, config_json, direction = None))]
    fn query(
        &self,
        py: Python<'_>,
        query: PyRef<'_, PyLandmark>,
        config_json: &str,
        direction: Option<[f64; 3]>,
    ) -> PyResult<PyQueryResult> {
        let cfg = config_from_json(config_json)?;
        let q = query.whole()?;
        let db = &self.inner;
        let inner = detached(py, move || match direction {
            Some(d) => db.query_directed(&q, &d, &cfg),
            None => db.query(&q, &cfg),
        })?;
        Ok(PyQueryResult { inner })
    }
    /// Every query against the database (batch mode), queries in parallel;
    /// `cross_session`: against an earlier survey (every entry eligible).
    #[pyo3(signature = (queries, config_json, cross_session = false))]
    fn query_batch(
        &self,
        py: Python<'_>,
        queries: Vec<PyRef<'_, PyLandmark>>,
        config_json: &str,
        cross_session: bool,
    ) -> PyResult<Vec<PyQueryResult>> {
        let cfg = config_from_json(config_json)?;
        let qs = held_of(&queries);
        let db = &self.inner;
        let eligibility = eligibility_of(cross_session, false);
        let results = detached(py, move || db.query_batch_held(&qs, &cfg, eligibility))?;
        Ok(results
            .into_iter()
            .map(|inner| PyQueryResult { inner })
            .collect())
    }
    /// Online mode: query against all stored landmarks, then add; returns (result, index).
    fn query_online(
        &mut self,
        py: Python<'_>,
        landmark: PyRef<'_, PyLandmark>,
        config_json: &str,
    ) -> PyResult<(PyQueryResult, usize)> {
        let cfg = config_from_json(config_json)?;
        let l = (*landmark.whole()?).clone();
        let db = &mut self.inner;
        let (inner, index) = detached(py, move || db.query_online(l, &cfg))?;
        Ok((PyQueryResult { inner }, index))
    }
    /// The stored landmark at `index`.
    fn landmark(&self, index: usize) -> PyResult<PyLandmark> {
        self.inner
            .get(index)
            .map(|l| PyLandmark::from_held(l.clone()))
            .ok_or_else(|| {
                pyo3::exceptions::PyIndexError::new_err(format!(
                    "landmark index {index} out of range (database holds {})",
                    self.inner.len()
                ))
            })
    }
    /// Writes the database as versioned JSON.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let db = &self.inner;
        detached(py, move || db.save(&path))
    }
    /// Reads a database; entries are prepared with `config_json` or the saved config.
    #[staticmethod]
    #[pyo3(signature = (path, config_json = None))]
    fn load(py: Python<'_>, path: PathBuf, config_json: Option<&str>) -> PyResult<Self> {
        let cfg = config_json.map(config_from_json).transpose()?;
        let inner = detached(py, move || LandmarkDatabase::load(&path, cfg.as_ref()))?;
        Ok(Self { inner })
    }
    /// The `[matching]` config the entries are prepared with, as JSON.
    fn config_json(&self) -> PyResult<String> {
        serde_json::to_string(self.inner.config())
            .map_err(|e| to_py_err(DecodError::config("matching", e.to_string())))
    }
    /// Bytes held per landmark (prepared data, coarse signature, boundary id).
    fn bytes_per_landmark(&self) -> usize {
        self.inner.bytes_per_landmark()
    }
    fn __len__(&self) -> usize {
        self.inner.len()
    }
}

/// The change between two sessions' views of one boundary (`decod::matching::change`):
/// `(normalised_difference, cells, difference)`, the candidate brought to the query by
/// `heading_deg` (0 or 180) and the pair's offsets; `difference` is `(rows, cols)`, NaN where
/// the two are not both observed.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn descriptor_change<'py>(
    py: Python<'py>,
    query: PyRef<'_, PyLandmark>,
    candidate: PyRef<'_, PyLandmark>,
    heading_deg: f64,
    dz_m: f64,
    dp: f64,
    config_json: &str,
) -> PyResult<(f64, usize, Bound<'py, PyArray2<f64>>)> {
    let cfg = config_from_json(config_json)?;
    let heading = if (heading_deg - 180.0).abs() < 1e-6 {
        Heading::Reversed
    } else if heading_deg.abs() < 1e-6 {
        Heading::Forward
    } else {
        return Err(to_py_err(DecodError::invalid(
            "heading_deg",
            format!("expected 0 or 180, got {heading_deg}"),
        )));
    };
    let (q, c) = (query.whole()?, candidate.whole()?);
    let (rows, cols) = (q.descriptor.rows, q.descriptor.cols);
    let change = detached(py, move || {
        matching::change::aligned_change(&q, &c, heading, dz_m, dp, &cfg)
    })?;
    let grid = flat_to_numpy(py, change.difference, rows, cols)?;
    Ok((change.normalised_difference, change.cells, grid))
}

/// A synthetic observation of joint `joint_seed` of pipe `pipe_seed` (see
/// `decod::matching::synthetic`): `grid` is "tunnel" or "pipe"; `random_view` draws noise,
/// misalignment and contour errors from `view_seed`; the rest are explicit overrides.
#[pyfunction]
#[pyo3(signature = (
    pipe_seed, joint_seed, *, stamp = 0.0, reversed = false, view_seed = 0, grid = "tunnel",
    random_view = true, shift_z_m = None, missing_arc = None, noise_m = None
))]
#[allow(clippy::too_many_arguments)]
fn synthetic_landmark(
    pipe_seed: u64,
    joint_seed: u64,
    stamp: f64,
    reversed: bool,
    view_seed: u64,
    grid: &str,
    random_view: bool,
    shift_z_m: Option<f64>,
    missing_arc: Option<(f64, f64)>,
    noise_m: Option<f64>,
) -> PyResult<PyLandmark> {
    let g = match grid {
        "tunnel" => Grid::tunnel(),
        "pipe" => Grid::pipe(),
        other => {
            return Err(to_py_err(DecodError::invalid(
                "grid",
                format!("{other:?} is not one of [\"tunnel\", \"pipe\"]"),
            )));
        }
    };
    let mut rng = Rng::new(view_seed);
    let mut obs = if random_view {
        Observation::random(&g, stamp, reversed, &mut rng)
    } else {
        Observation {
            stamp,
            reversed,
            ..Observation::default()
        }
    };
    if let Some(s) = shift_z_m {
        obs.shift_z_m = s;
    }
    obs.missing_arc = missing_arc;
    if let Some(n) = noise_m {
        obs.noise_m = n;
    }
    let joint = JointSurface::new(g, SurfaceParams::for_grid(&g), pipe_seed, joint_seed);
    Ok(PyLandmark::new(
        joint.observe(&obs, view_seed.wrapping_add(1)),
    ))
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyPairResult>()?;
    m.add_class::<PyQueryResult>()?;
    m.add_class::<PyLandmarkDatabase>()?;
    m.add_class::<PyPreparedViews>()?;
    m.add_function(wrap_pyfunction!(compare, m)?)?;
    m.add_function(wrap_pyfunction!(compare_pairs, m)?)?;
    m.add_function(wrap_pyfunction!(descriptor_change, m)?)?;
    m.add_function(wrap_pyfunction!(synthetic_landmark, m)?)?;
    Ok(())
}
