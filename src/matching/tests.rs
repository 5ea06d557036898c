//! End-to-end matcher tests on synthetic descriptors (`synthetic.rs`). Tolerances: K is
//! compared with the config's `min_inliers` (the acceptance threshold itself); offsets with
//! half a cell (keypoints sit on cell centres).

use super::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};
use super::*;
use crate::config::DecodConfig;

fn cfg() -> MatchingConfig {
    DecodConfig::tunnel().matching
}

fn joint(pipe: u64, id: u64) -> JointSurface {
    let g = Grid::tunnel();
    JointSurface::new(g, SurfaceParams::for_grid(&g), pipe, id)
}

fn later(stamp: f64) -> Observation {
    Observation {
        stamp,
        ..Observation::default()
    }
}

fn assert_match(a: &Landmark, b: &Landmark, heading: Heading) -> PairResult {
    let r = compare(a, b, &cfg()).unwrap();
    assert_eq!(r.heading, heading, "{r:?}");
    assert!(r.inliers >= cfg().min_inliers, "{r:?}");
    assert!(r.rejection.is_none(), "{r:?}");
    r
}

#[test]
fn same_boundary_twice_with_different_noise() {
    let j = joint(1, 1);
    let r = assert_match(
        &j.observe(&Observation::default(), 1),
        &j.observe(&later(100.0), 2),
        Heading::Forward,
    );
    assert!(r.dz_m.abs() < 0.15 && r.dp.abs() < 1.0 / 256.0, "{r:?}");
}

#[test]
fn half_the_circumference_missing() {
    let j = joint(1, 2);
    let half = Observation {
        // The lower half (p = 0 is the gravity side): sediment or water in a pipe.
        missing_arc: Some((0.75, 0.5)),
        ..later(100.0)
    };
    let r = assert_match(
        &j.observe(&Observation::default(), 1),
        &j.observe(&half, 2),
        Heading::Forward,
    );
    assert!(r.overlap_fraction < 0.5, "{r:?}");
}

#[test]
fn one_cell_axial_misalignment() {
    let j = joint(1, 3);
    let cell = Grid::tunnel().cell_z_m;
    let shifted = Observation {
        shift_z_m: cell,
        ..later(100.0)
    };
    let r = assert_match(
        &j.observe(&Observation::default(), 1),
        &j.observe(&shifted, 2),
        Heading::Forward,
    );
    // The query's feature at z lies at z - cell in the shifted view (its origin moved +cell).
    assert!((r.dz_m + cell).abs() < 0.5 * cell, "{r:?}");
}

#[test]
fn contour_tilt_and_centring_error() {
    let j = joint(1, 4);
    let distorted = Observation {
        tilt: [0.02, -0.015],
        centring_m: [0.05, -0.04],
        radius_error_m: 0.03,
        ellipticity_m: 0.02,
        ..later(100.0)
    };
    assert_match(
        &j.observe(&Observation::default(), 1),
        &j.observe(&distorted, 2),
        Heading::Forward,
    );
}

#[test]
fn reversed_heading() {
    let j = joint(1, 5);
    let cell = Grid::tunnel().cell_z_m;
    let back = Observation {
        reversed: true,
        shift_z_m: cell,
        ..later(100.0)
    };
    let r = assert_match(
        &j.observe(&Observation::default(), 1),
        &j.observe(&back, 2),
        Heading::Reversed,
    );
    assert!((r.dz_m + cell).abs() < 0.5 * cell, "{r:?}");
}

#[test]
fn different_boundaries_of_the_same_pipe_do_not_match() {
    for k in 0..5 {
        let a = joint(1, 10 + k).observe(&Observation::default(), 1);
        let b = joint(1, 20 + k).observe(&later(100.0), 2);
        let r = compare(&a, &b, &cfg()).unwrap();
        assert!(r.inliers < cfg().min_inliers, "{r:?}");
        assert_eq!(r.rejection, Some(Rejection::TooFewInliers));
    }
}

/// A database of `n` joints seen outbound; `ids[k]` picks the joint seed of entry `k`.
fn corridor(ids: &[u64], rng: &mut Rng) -> LandmarkDatabase {
    let g = Grid::tunnel();
    let mut db = LandmarkDatabase::new(&cfg());
    for (k, &id) in ids.iter().enumerate() {
        let obs = Observation::random(&g, 10.0 * k as f64, false, rng);
        db.add(joint(3, id).observe(&obs, 1000 + k as u64)).unwrap();
    }
    db
}

#[test]
fn aliased_corridor_yields_no_accepted_loop() {
    let mut rng = Rng::new(11);
    // Five identical precast joints (same geometry, different noise and views).
    let db = corridor(&[7; 5], &mut rng);
    // The paper's trajectory threshold (9), not the tunnel preset's 16: aliased pairs reach
    // K = 13 here, and it is the uniqueness test, not the count, that must reject them.
    let cfg = MatchingConfig {
        min_inliers: 9,
        ..cfg()
    };
    for t in 0..4 {
        let obs = Observation::random(&Grid::tunnel(), 1000.0 + t as f64, t % 2 == 1, &mut rng);
        let q = joint(3, 7).observe(&obs, 50 + t);
        let r = db.query(&q, &cfg).unwrap();
        let ratio = r.pair.as_ref().unwrap().score / r.runner_up_score;
        eprintln!(
            "aliased: best/runner-up = {ratio:.3} (K {} vs {})",
            r.pair.as_ref().unwrap().inliers,
            r.runner_up_inliers
        );
        assert!(!r.accepted, "{r:?}");
        assert_eq!(r.rejection, Some(Rejection::NotUnique));
    }
}

#[test]
fn corridor_of_similar_joints_is_matched() {
    let mut rng = Rng::new(12);
    let ids = [30, 31, 32, 33, 34, 35];
    let db = corridor(&ids, &mut rng);
    for (k, &id) in ids.iter().enumerate() {
        let obs = Observation::random(&Grid::tunnel(), 1000.0 + k as f64, k % 2 == 0, &mut rng);
        let r = db
            .query(&joint(3, id).observe(&obs, 70 + k as u64), &cfg())
            .unwrap();
        let p = r.pair.as_ref().unwrap();
        eprintln!(
            "similar: best/runner-up = {:.3} (K {} vs {})",
            p.score / r.runner_up_score.max(1e-9),
            p.inliers,
            r.runner_up_inliers
        );
        assert!(r.accepted, "{r:?}");
        assert_eq!(r.candidate_index, Some(k));
        assert_eq!(
            r.heading(),
            if k % 2 == 0 {
                Heading::Reversed
            } else {
                Heading::Forward
            }
        );
    }
}

#[test]
fn serial_and_parallel_queries_agree() {
    let mut rng = Rng::new(13);
    let db = corridor(&[40, 41, 42, 43, 44, 45, 46, 47], &mut rng);
    for k in 0..4u64 {
        let obs = Observation::random(&Grid::tunnel(), 500.0, k % 2 == 1, &mut rng);
        let q = joint(3, 40 + 2 * k).observe(&obs, 90 + k);
        assert_eq!(
            db.query(&q, &cfg()).unwrap(),
            db.query_serial(&q, &cfg()).unwrap()
        );
    }
}

#[test]
fn eligibility_excludes_close_and_overlapping_submaps() {
    let j = joint(1, 6);
    let mut db = LandmarkDatabase::new(&cfg());
    db.add(j.observe(&Observation::default(), 1)).unwrap();
    let close = db.query(&j.observe(&later(10.0), 2), &cfg()).unwrap();
    assert_eq!(close.rejection, Some(Rejection::Ineligible));
    assert_eq!(close.eligible, 0);
    let mut shared = j.observe(&later(100.0), 3);
    shared.scan_stamps.push(0.5); // a scan of the database submap
    assert_eq!(db.query(&shared, &cfg()).unwrap().eligible, 0);
    let far = db.query(&j.observe(&later(100.0), 4), &cfg()).unwrap();
    assert!(far.accepted, "{far:?}");
}

#[test]
fn across_passes_drops_the_time_separation_but_not_shared_scans() {
    // Batch mode: the return pass queries the outbound pass, so a boundary seen by both
    // within `min_time_separation_s` (near the turnaround) is a candidate; a submap that
    // shares a scan with the query never is.
    let c = cfg();
    let j = joint(1, 6);
    let mut db = LandmarkDatabase::new(&c);
    db.add(j.observe(&Observation::default(), 1)).unwrap();
    let prepare = |l: Landmark| {
        let shape = patches::PatchShape::new(&c);
        PreparedLandmark::new_query(Arc::new(l), &c, &shape).unwrap()
    };
    let close = prepare(j.observe(&later(10.0), 2));
    let mut shared = j.observe(&later(10.0), 3);
    shared.scan_stamps.push(0.5); // a scan of the database submap
    let shared = prepare(shared);
    let queries = [&close, &shared];
    let within = db
        .query_batch_prepared(&queries, None, &c, database::Eligibility::WithinRun)
        .unwrap();
    assert!(within.iter().all(|r| r.eligible == 0), "{within:?}");
    let across = db
        .query_batch_prepared(&queries, None, &c, database::Eligibility::AcrossPasses)
        .unwrap();
    assert_eq!(across[0].eligible, 1);
    assert!(across[0].accepted, "{:?}", across[0]);
    assert_eq!(across[1].eligible, 0);
}

#[test]
fn gemm_patch_distances_agree_with_brute_force() {
    let c = cfg();
    let shape = patches::PatchShape::new(&c);
    let j = joint(2, 1);
    let a = j.observe(
        &Observation {
            holes: 6,
            ..Observation::default()
        },
        1,
    );
    let b = joint(2, 2).observe(
        &Observation {
            holes: 6,
            missing_arc: Some((0.1, 0.3)),
            ..later(100.0)
        },
        2,
    );
    let mode = normalise::Normalisation::from_config(&c);
    // Each side's field, keypoints and their f64 reference patches.
    let patches_of = |l: &Landmark| {
        let d = &l.descriptor;
        let field = normalise::normalised_field(d, mode, false);
        let kps = keypoints::detect(&field, &d.observed, d.rows, d.cols, &c, |r, col| {
            shape.coverage(&d.observed, (d.rows, d.cols), r, col)
        });
        let compact =
            patches::CandidatePatches::new(&shape, &field, &d.observed, (d.rows, d.cols), &kps);
        let reference = kps
            .iter()
            .map(|k| shape.extract(&field, &d.observed, (d.rows, d.cols), k))
            .collect::<Vec<_>>();
        (compact, reference)
    };
    let ((own, pa), (cand, pb)) = (patches_of(&a), patches_of(&b));
    // The compact patches are the f64 reference's from a field rounded to f32.
    let mut patch = vec![0.0f32; shape.len()];
    for (j, (values, mask)) in pb.iter().enumerate() {
        cand.patch_into(&shape, j, &mut patch);
        for k in 0..shape.len() {
            if mask[k] {
                assert!((f64::from(patch[k]) - values[k]).abs() < 1e-4, "{k}");
            } else {
                assert!(patch[k].is_nan(), "{k}");
            }
        }
    }
    // The data reach every block of the products: banded patches (whole, and cut by an
    // axial end) and patches with holes, on both sides.
    for side in [&own, &cand] {
        let banded = (0..side.count()).filter(|&k| side.is_banded(k)).count();
        let cut = (0..side.count())
            .filter(|&k| side.is_banded(k) && side.rows_within(&shape, k) != (0, shape.rows))
            .count();
        assert!(
            banded > 5 && cut > 0 && banded < side.count() - 5,
            "{banded} {cut}"
        );
    }
    assert_distances_match_reference(&shape, &own, &pa, &cand, &pb, c.min_patch_overlap_fraction);
}

/// Every patch distance of `own` (query, both headings) against `cand` agrees with the f64
/// brute force over the reference patches `pa`, `pb`.
fn assert_distances_match_reference(
    shape: &patches::PatchShape,
    own: &patches::CandidatePatches,
    pa: &[(Vec<f64>, Vec<bool>)],
    cand: &patches::CandidatePatches,
    pb: &[(Vec<f64>, Vec<bool>)],
    min_overlap: f64,
) {
    let factor = patch_distances::PatchFactor::new(shape, cand);
    for flipped in [false, true] {
        let query = patch_distances::QueryPatches::from_candidate(shape, own, flipped);
        let dist = patch_distances::distances(shape, &query, &factor, min_overlap);
        let mut finite = 0;
        for (i, qa) in pa.iter().enumerate() {
            let qa = if flipped {
                (
                    qa.0.iter().rev().copied().collect(),
                    qa.1.iter().rev().copied().collect(),
                )
            } else {
                qa.clone()
            };
            for (jj, qb) in pb.iter().enumerate() {
                let want = patches::distance_reference(shape, &qa, qb, min_overlap);
                let got = f64::from(dist.get(i, jj).unwrap());
                if want.is_finite() {
                    finite += 1;
                    // z-scored patches: distances ~1; f32 GEMM over ~900 terms: ~1e-5.
                    assert!((got - want).abs() < 1e-4 * (1.0 + want), "{got} vs {want}");
                } else {
                    assert!(got.is_infinite(), "{got} vs inf");
                }
            }
        }
        assert!(finite > pa.len() * pb.len() / 4, "{finite}");
    }
}

#[test]
fn patch_distances_of_banded_patches_at_the_axial_ends_agree_with_brute_force() {
    // Keypoints on every row of a 16-row field, on a hole and beside it: banded patches of
    // every band (cut by either axial end or whole) meet each other and patches with holes,
    // under both headings.
    let c = cfg();
    let shape = patches::PatchShape::new(&c);
    let grid = (16, 96);
    let fields: Vec<Vec<f64>> = (0..2)
        .map(|s| {
            (0..grid.0 * grid.1)
                .map(|i| ((i * (7 + 4 * s) + i / grid.1 * 3) % 17) as f64 * 0.1 - 0.8)
                .collect()
        })
        .collect();
    let observed: Vec<bool> = (0..grid.0 * grid.1)
        .map(|i| !((5..8).contains(&(i / grid.1)) && (40..52).contains(&(i % grid.1))))
        .collect();
    let centres: Vec<(usize, usize)> = (0..grid.0)
        .flat_map(|r| [(r, 5 + 3 * r), (r, 46), (r, 70 + r)])
        .collect();
    let kps = keypoints_at(&centres);
    let side = |field: &[f64]| {
        let compact = patches::CandidatePatches::new(&shape, field, &observed, grid, &kps);
        let reference: Vec<_> = kps
            .iter()
            .map(|k| shape.extract(field, &observed, grid, k))
            .collect();
        (compact, reference)
    };
    let ((own, pa), (cand, pb)) = (side(&fields[0]), side(&fields[1]));
    let bands: std::collections::BTreeSet<_> = (0..own.count())
        .filter(|&k| own.is_banded(k))
        .map(|k| own.rows_within(&shape, k))
        .collect();
    assert_eq!(bands.len(), 9, "{bands:?}");
    assert!((0..own.count()).any(|k| !own.is_banded(k)));
    assert_distances_match_reference(&shape, &own, &pa, &cand, &pb, c.min_patch_overlap_fraction);
}

/// Keypoints at `(row, col)` centres (the patch tests place them by hand).
fn keypoints_at(centres: &[(usize, usize)]) -> Vec<keypoints::Keypoint> {
    centres
        .iter()
        .map(|&(row, col)| keypoints::Keypoint {
            row,
            col,
            response: 1.0,
        })
        .collect()
}

#[test]
fn candidate_factor_is_the_same_from_a_reused_buffer() {
    // A comparison builds the candidate's factor in its thread's buffer, left over from the
    // last pair: what that pair wrote (other values, more keypoints) must not reach this one.
    let shape = patches::PatchShape::new(&cfg());
    let p = shape.len();
    // A 12 x 80 field of small integers with holes in its first half, five keypoints (one
    // near the axial end, one whose patch wraps around the circumference, two in the half
    // without holes: banded, whole and cut by the axial end).
    let grid = (12, 80);
    let field: Vec<f64> = (0..grid.0 * grid.1)
        .map(|i| ((i * 7) % 13) as f64 - 6.0)
        .collect();
    let observed: Vec<bool> = (0..field.len())
        .map(|i| i % 5 != 0 || i % grid.1 >= 40)
        .collect();
    let kps = keypoints_at(&[(6, 20), (2, 3), (8, 38), (6, 60), (1, 58)]);
    let cand = patches::CandidatePatches::new(&shape, &field, &observed, grid, &kps);
    let fresh = patch_distances::PatchFactor::new(&shape, &cand);
    let other: Vec<f64> = field.iter().map(|v| v * 0.5 + 1.0).collect();
    let mut reused = patch_distances::PatchFactor::new(
        &shape,
        &patches::CandidatePatches::new(
            &shape,
            &other,
            &observed,
            grid,
            &keypoints_at(&[(5, 5); 10]),
        ),
    );
    reused.fill(&shape, &cand);
    assert_eq!(
        (reused.matrix().nrows(), reused.matrix().ncols()),
        (3 * p, 5)
    );
    // Banded first, then the rest, each in the keypoints' order.
    let order: Vec<usize> = (0..5).map(|col| fresh.keypoint(col)).collect();
    assert_eq!(order, [3, 4, 0, 1, 2]);
    for col in 0..5 {
        assert_eq!(reused.keypoint(col), order[col]);
        let kp = &kps[order[col]];
        // Small integers and their z-score: the f32 field is exact, so are the values.
        let (values, mask) = shape.extract(&field, &observed, grid, kp);
        assert_eq!(mask.iter().all(|&m| m), col == 0, "{col}");
        for k in 0..p {
            let b = values[k] as f32;
            let want = if mask[k] {
                [1.0, shape.weights[k] * b * b, -2.0 * b]
            } else {
                [0.0; 3]
            };
            for (block, w) in want.iter().enumerate() {
                let row = block * p + k;
                let (got, again) = (fresh.matrix()[(row, col)], reused.matrix()[(row, col)]);
                assert_eq!(got.to_bits(), w.to_bits(), "cell {k}, block {block}");
                assert_eq!(
                    again.to_bits(),
                    w.to_bits(),
                    "reused: cell {k}, block {block}"
                );
            }
        }
    }
    // The band sums too: the same distances bit for bit.
    let query = patch_distances::QueryPatches::from_candidate(&shape, &cand, false);
    let (d1, d2) = (
        patch_distances::distances(&shape, &query, &fresh, 0.5),
        patch_distances::distances(&shape, &query, &reused, 0.5),
    );
    for i in 0..5 {
        for j in 0..5 {
            let (x, y) = (d1.get(i, j).unwrap(), d2.get(i, j).unwrap());
            assert_eq!(x.to_bits(), y.to_bits(), "{i} {j}");
        }
    }
}

#[test]
fn patches_read_out_of_a_field_narrower_than_a_patch_wrap_cell_by_cell() {
    // 33-column patches on a 20-column field: every patch row wraps around more than once
    // at its ends; the values must still be the f64 reference's (exact on small integers).
    let shape = patches::PatchShape::new(&cfg());
    let grid = (10, 20);
    let field: Vec<f64> = (0..grid.0 * grid.1)
        .map(|i| (i % 11) as f64 - 5.0)
        .collect();
    let observed: Vec<bool> = (0..field.len()).map(|i| i % 7 != 3).collect();
    let kps = keypoints_at(&[(0, 0), (5, 19), (9, 7)]);
    let cand = patches::CandidatePatches::new(&shape, &field, &observed, grid, &kps);
    let mut patch = vec![0.0f32; shape.len()];
    for (j, kp) in kps.iter().enumerate() {
        cand.patch_into(&shape, j, &mut patch);
        let (values, mask) = shape.extract(&field, &observed, grid, kp);
        for k in 0..shape.len() {
            if mask[k] {
                assert_eq!(patch[k].to_bits(), (values[k] as f32).to_bits(), "{j}: {k}");
            } else {
                assert!(patch[k].is_nan(), "{j}: {k}");
            }
        }
    }
}

#[test]
fn database_round_trips_and_rejects_other_versions() {
    let mut rng = Rng::new(14);
    let mut db = corridor(&[50, 51, 52], &mut rng);
    // Two of the three placed; the third stays unplaced through the round trip.
    db.set_positions(&[0, 2], &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
        .unwrap();
    let dir = std::env::temp_dir().join(format!("decod-db-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("db.json");
    db.save(&path).unwrap();
    let back = LandmarkDatabase::load(&path, None).unwrap();
    assert_eq!(back.len(), 3);
    assert_eq!(back.positions()[0], [1.0, 2.0, 3.0]);
    assert_eq!(back.positions()[2], [4.0, 5.0, 6.0]);
    assert!(back.positions()[1].iter().all(|v| v.is_nan()));
    let q = joint(3, 51).observe(
        &Observation::random(&Grid::tunnel(), 900.0, true, &mut rng),
        5,
    );
    assert_eq!(
        db.query(&q, &cfg()).unwrap(),
        back.query(&q, &cfg()).unwrap()
    );
    let text = std::fs::read_to_string(&path).unwrap();
    let bumped = text.replacen("\"version\":1", "\"version\":99", 1);
    std::fs::write(&path, bumped).unwrap();
    let err = LandmarkDatabase::load(&path, None).unwrap_err();
    assert!(matches!(err, DecodError::Database { .. }), "{err}");
    assert!(err.to_string().contains("version 99"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Precision/recall of the whole query path on `n` joints of one pipe, each seen outbound
/// (database) and on the return traversal (queries, reversed heading), random views.
pub(crate) fn precision_recall(c: &MatchingConfig, n: u64, seed: u64) -> (f64, f64, usize) {
    let g = Grid::tunnel();
    let mut rng = Rng::new(seed);
    let mut db = LandmarkDatabase::new(c);
    let outbound: Vec<Landmark> = (0..n)
        .map(|k| {
            joint(seed, k).observe(&Observation::random(&g, 8.0 * k as f64, false, &mut rng), k)
        })
        .collect();
    db.extend(outbound).unwrap();
    let queries: Vec<Landmark> = (0..n)
        .map(|k| {
            let obs = Observation::random(&g, 2000.0 - 8.0 * k as f64, true, &mut rng);
            joint(seed, k).observe(&obs, 10_000 + k)
        })
        .collect();
    let results = db.query_batch(&queries, c).unwrap();
    let accepted = results.iter().filter(|r| r.accepted).count();
    let correct = results
        .iter()
        .enumerate()
        .filter(|(k, r)| r.accepted && r.candidate_index == Some(*k))
        .count();
    let precision = if accepted > 0 {
        correct as f64 / accepted as f64
    } else {
        1.0
    };
    (precision, correct as f64 / n as f64, accepted)
}

#[test]
fn precision_and_recall_on_fifty_joints() {
    let (p, r, a) = precision_recall(&cfg(), 50, 21);
    eprintln!("paper config: precision {p:.3} recall {r:.3} accepted {a}");
    // Distinct joints with realistic nuisances: every accepted loop must be right and
    // most found. The count margin of the uniqueness test (`uniqueness_sigma`) trades weak
    // true loops for safety against aliasing: recall 0.98 without it, 0.92 with the preset's
    // (seed 21); below 0.85 the detector or verification regressed.
    assert!(p == 1.0, "precision {p}");
    assert!(r >= 0.85, "recall {r}");
}

#[test]
fn ablations_run_and_verification_keeps_precision() {
    // The paper's ablations on the 50-joint set; figures go to the issue note. Without
    // verification every query is accepted (no K check, no uniqueness), so its precision
    // cannot exceed the verified matcher's.
    let (p_full, r_full, a_full) = precision_recall(&cfg(), 50, 22);
    let mut figures = vec![format!("recall {r_full:.3} accepted {a_full}")];
    for (name, tweak) in [
        (
            "k15",
            (|c: &mut MatchingConfig| c.min_inliers = 15) as fn(&mut MatchingConfig),
        ),
        ("no_verification", |c| c.verification = false),
        ("scale_only", |c| c.normalisation = "scale_only".into()),
        ("sign_only", |c| c.sign_only = true),
    ] {
        let mut c = cfg();
        tweak(&mut c);
        let (p, r, a) = precision_recall(&c, 50, 22);
        figures.push(format!(
            "{name}: precision {p:.3} recall {r:.3} accepted {a}"
        ));
        if name == "no_verification" {
            assert_eq!(a, 50);
            assert!(p <= p_full);
        }
    }
    eprintln!("paper config precision {p_full:.3}; {}", figures.join("; "));
}

#[test]
fn runner_up_exclusion_lets_two_views_of_one_joint_through() {
    let j = joint(1, 8);
    let mut db = LandmarkDatabase::new(&cfg());
    db.add(j.observe(&Observation::default(), 1)).unwrap();
    db.add(j.observe(&later(8.0), 2)).unwrap(); // the same joint, next submap
    let q = j.observe(&later(500.0), 3);
    assert_eq!(
        db.query(&q, &cfg()).unwrap().rejection,
        Some(Rejection::NotUnique)
    );
    let mut c = cfg();
    c.runner_up_exclusion_s = 10.0;
    let r = db.query(&q, &c).unwrap();
    assert!(r.accepted, "{r:?}");
    assert_eq!(r.runner_up_index, None);
}

#[test]
fn pipe_grid_matches_and_degenerate_input_is_handled() {
    let g = Grid::pipe();
    let j = JointSurface::new(g, SurfaceParams::for_grid(&g), 4, 1);
    let mut rng = Rng::new(3);
    let a = j.observe(&Observation::random(&g, 0.0, false, &mut rng), 1);
    let b = j.observe(&Observation::random(&g, 100.0, true, &mut rng), 2);
    let pipe = DecodConfig::pipe().matching;
    let r = compare(&a, &b, &pipe).unwrap();
    assert_eq!(r.heading, Heading::Reversed);
    assert!(r.inliers >= pipe.min_inliers, "{r:?}");
    // Nothing observed: no keypoints, a clean rejection, no panic.
    let mut blind = b.clone();
    blind
        .descriptor
        .observed
        .iter_mut()
        .for_each(|o| *o = false);
    blind.descriptor.offsets_m.iter_mut().for_each(|v| *v = 0.0);
    let r = compare(&a, &blind, &pipe).unwrap();
    assert_eq!(r.rejection, Some(Rejection::InsufficientOverlap));
    // Another grid: a named error.
    let mut small = b.clone();
    small.descriptor.rows = 8;
    small.descriptor.offsets_m.truncate(8 * 256);
    small.descriptor.observed.truncate(8 * 256);
    assert!(matches!(
        compare(&a, &small, &pipe),
        Err(DecodError::InvalidInput { .. })
    ));
}

/// Queries of one pipe's joints against a database of another pipe's joints (every Top-1 is
/// wrong): the fraction accepted, over `queries` queries against `n` candidates.
fn false_accept_rate(c: &MatchingConfig, n: u64, queries: u64, seed: u64) -> f64 {
    let g = Grid::tunnel();
    let mut rng = Rng::new(seed);
    let mut db = LandmarkDatabase::new(c);
    let other: Vec<Landmark> = (0..n)
        .map(|k| joint(seed, k).observe(&Observation::random(&g, k as f64, false, &mut rng), k))
        .collect();
    db.extend(other).unwrap();
    let qs: Vec<Landmark> = (0..queries)
        .map(|k| {
            let obs = Observation::random(&g, 1e5 + k as f64, k % 2 == 0, &mut rng);
            joint(seed + 1000, k).observe(&obs, 50_000 + k)
        })
        .collect();
    let results = db.query_batch(&qs, c).unwrap();
    results.iter().filter(|r| r.accepted).count() as f64 / queries as f64
}

#[test]
fn null_model_rejects_unrelated_pairs_at_the_promised_rate() {
    // A lax promise (5 % of queries may accept a wrong Top-1 by chance) so a finite test can
    // see violations: 200 queries, binomial sd 1.5 %; the bound holds with 3 sd to spare.
    for (cap, n) in [(16, 20), (64, 20), (64, 400)] {
        let c = MatchingConfig {
            max_keypoints: cap,
            false_alarm_rate: 0.05,
            ..cfg()
        };
        let rate = false_accept_rate(&c, n, 200, 31 + cap as u64);
        eprintln!("null model: {cap} keypoints, {n} candidates: false accepts {rate:.3}");
        assert!(
            rate <= 0.05 + 3.0 * (0.05f64 * 0.95 / 200.0).sqrt(),
            "{rate}"
        );
    }
}

#[test]
fn null_model_keeps_true_loops_for_any_keypoint_count() {
    for cap in [16, 32, 64] {
        let c = MatchingConfig {
            max_keypoints: cap,
            ..cfg()
        };
        let (p, r, a) = precision_recall(&c, 50, 23);
        eprintln!("null model, {cap} keypoints: precision {p:.3} recall {r:.3} accepted {a}");
        assert!(p == 1.0, "precision {p}");
        // With 16 keypoints a true pair has K = 5-12 and the null model's floor
        // (`min_inliers_floor` = 6) costs the weakest: recall 0.58 (seed 23), against 1.0 with
        // 32 and 64. Half the joints is the floor of "keeps true loops" here.
        assert!(r >= 0.5, "recall {r} with {cap} keypoints");
    }
}

#[test]
fn views_of_one_boundary_are_one_candidate() {
    let j = joint(1, 8);
    let other = joint(1, 9);
    let mut db = LandmarkDatabase::new(&cfg());
    // Two views of joint 8 (boundary 0) and one of joint 9 (boundary 1).
    db.add_view(j.observe(&Observation::default(), 1), 0)
        .unwrap();
    db.add_view(j.observe(&later(8.0), 2), 0).unwrap();
    db.add_view(other.observe(&later(16.0), 4), 1).unwrap();
    let r = db.query(&j.observe(&later(500.0), 3), &cfg()).unwrap();
    assert!(r.accepted, "{r:?}");
    assert_eq!(r.runner_up_index, Some(2));
    // The same views as separate boundaries: the second view is a strong runner-up.
    let mut separate = LandmarkDatabase::new(&cfg());
    separate
        .extend(vec![
            j.observe(&Observation::default(), 1),
            j.observe(&later(8.0), 2),
        ])
        .unwrap();
    let r = separate
        .query(&j.observe(&later(500.0), 3), &cfg())
        .unwrap();
    assert_eq!(r.rejection, Some(Rejection::NotUnique));
    assert!(matches!(
        db.extend_views(vec![j.observe(&later(30.0), 5)], vec![]),
        Err(DecodError::InvalidInput { .. })
    ));
}

/// Two views of joint 8 entered as two boundaries, the second's origin one row along the
/// axis (as a neighbouring ring aligns, one ring's shift away), placed at `second_at` (none:
/// unplaced, as in a survey's database); and a query of the joint.
fn two_boundaries_one_place(second_at: Option<f64>) -> (LandmarkDatabase, Landmark) {
    let j = joint(1, 8);
    let cell = Grid::tunnel().cell_z_m;
    let shifted = Observation {
        shift_z_m: cell,
        ..later(8.0)
    };
    let mut db = LandmarkDatabase::new(&cfg());
    db.extend(vec![
        j.observe(&Observation::default(), 1),
        j.observe(&shifted, 2),
    ])
    .unwrap();
    if let Some(x) = second_at {
        db.set_positions(&[0, 1], &[[0.0, 0.0, 0.0], [x, 0.0, 0.0]])
            .unwrap();
        db.set_directions(&[0, 1], &[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
            .unwrap();
    }
    (db, j.observe(&later(500.0), 3))
}

#[test]
fn a_runner_up_that_names_the_same_place_is_not_a_competitor() {
    let cell = Grid::tunnel().cell_z_m;
    // The second entry's origin is one row further along the axis, and its pair's offset
    // brings it back: both candidates put the query at x = 0.
    let (db, q) = two_boundaries_one_place(Some(cell));
    let r = db.query(&q, &cfg()).unwrap();
    assert!(r.accepted, "{r:?}");
    assert_eq!(r.runner_up_index, None, "{r:?}");
    // The rule off: the second view is a strong runner-up, as before.
    let mut off = cfg();
    off.runner_up_same_place_rows = 0.0;
    let r = db.query(&q, &off).unwrap();
    assert_eq!(r.rejection, Some(Rejection::NotUnique), "{r:?}");
    // The same surface 1.5 m away (an identical joint elsewhere): another place, aliased.
    let (db, q) = two_boundaries_one_place(Some(1.5 + cell));
    let r = db.query(&q, &cfg()).unwrap();
    assert_eq!(r.rejection, Some(Rejection::NotUnique), "{r:?}");
    // Unplaced entries (a survey's database) are never merged.
    let (unplaced, q) = two_boundaries_one_place(None);
    let r = unplaced.query(&q, &cfg()).unwrap();
    assert_eq!(r.rejection, Some(Rejection::NotUnique), "{r:?}");
}

/// A database of `n` distinct joints of one pipe (one view each) on `grid`, and `queries`
/// revisits of some of them (half reversed) plus as many queries of joints it does not hold.
fn retrieval_set(grid: Grid, n: u64, queries: u64, seed: u64) -> (Vec<Landmark>, Vec<Landmark>) {
    let mut rng = Rng::new(seed);
    let surface = |id: u64| JointSurface::new(grid, SurfaceParams::for_grid(&grid), 9, id);
    let db = (0..n)
        .map(|k| surface(k).observe(&Observation::random(&grid, k as f64, false, &mut rng), k))
        .collect();
    let qs = (0..2 * queries)
        .map(|t| {
            // Even t: a joint of the database; odd t: one it does not hold.
            let id = if t % 2 == 0 { (t * 7) % n } else { n + t };
            let obs = Observation::random(&grid, 1e5 + t as f64, t % 4 < 2, &mut rng);
            surface(id).observe(&obs, 10_000 + t)
        })
        .collect();
    (db, qs)
}

#[test]
fn coarse_short_list_keeps_the_exhaustive_top1() {
    // The criterion: the short list holds the exhaustive Top-1 in >= 99 % of the
    // queries whose Top-1 is a real match (verified: the pair passes on its own), and the
    // coarse Top-1 recall is within a point of the exhaustive one. Queries of joints the
    // database does not hold have no meaningful Top-1 (the best of chance agreements) and
    // must stay rejected under both.
    for (grid, mut c) in [
        (Grid::tunnel(), DecodConfig::tunnel().matching),
        (Grid::pipe(), DecodConfig::pipe().matching),
    ] {
        let (db_landmarks, queries) = retrieval_set(grid, 400, 50, 31);
        let mut db = LandmarkDatabase::new(&c);
        db.extend(db_landmarks).unwrap();
        c.retrieval = "exhaustive".into();
        let exhaustive = db.query_batch(&queries, &c).unwrap();
        c.retrieval = "coarse".into();
        c.retrieval_min_candidates = 0;
        c.retrieval_short_list = 32;
        let coarse = db.query_batch(&queries, &c).unwrap();
        let (mut verified, mut kept, mut acc_e, mut acc_c) = (0, 0, 0, 0);
        for (t, (e, q)) in exhaustive.iter().zip(&coarse).enumerate() {
            let real = e.pair.as_ref().is_some_and(|p| p.rejection.is_none());
            if real {
                verified += 1;
                kept += usize::from(q.candidate_index == e.candidate_index);
            }
            acc_e += usize::from(e.accepted && t % 2 == 0);
            acc_c += usize::from(q.accepted && t % 2 == 0);
            if t % 2 == 1 {
                assert!(!q.accepted && !e.accepted, "unheld joint accepted: {q:?}");
            }
            // Acceptance is as strict: the family counts every eligible boundary.
            assert_eq!(q.eligible, e.eligible);
        }
        eprintln!(
            "coarse ({} grid): short list holds the exhaustive Top-1 in {kept}/{verified}; \
             accepted true queries exhaustive {acc_e}, coarse {acc_c} of 50",
            grid.cols
        );
        assert!(verified >= 40, "{verified}");
        assert!(kept as f64 >= 0.99 * verified as f64, "{kept}/{verified}");
        assert!(acc_c + 1 >= acc_e, "{acc_c} vs {acc_e}");
    }
}

#[test]
fn short_list_is_widened_by_the_boundaries_beside_its_best() {
    // Forty distinct joints 10 m apart and a twin of joint 7 (the same surface: a ring
    // that shares its wall with the next) 1 m beside it. A short list of one holds only one
    // of the two; the uniqueness test must still see the other, as the exhaustive matcher
    // does, once the database knows where its boundaries lie.
    let grid = Grid::tunnel();
    let mut rng = Rng::new(23);
    let surface = |id: u64| JointSurface::new(grid, SurfaceParams::for_grid(&grid), 4, id);
    let mut landmarks: Vec<Landmark> = (0..40)
        .map(|k| surface(k).observe(&Observation::random(&grid, k as f64, false, &mut rng), k))
        .collect();
    landmarks.push(surface(7).observe(&Observation::random(&grid, 40.0, false, &mut rng), 40));
    let extent = grid.rows as f64 * grid.cell_z_m;
    let at = |twin_offset: f64| -> Vec<[f64; 3]> {
        (0..40)
            .map(|k| [10.0 * k as f64, 0.0, 0.0])
            .chain([[70.0 + twin_offset, 0.0, 0.0]])
            .collect()
    };
    let c = MatchingConfig {
        min_inliers: 9,
        retrieval: "coarse".into(),
        retrieval_min_candidates: 0,
        retrieval_short_list: 1,
        ..cfg()
    };
    let exhaustive = MatchingConfig {
        retrieval: "exhaustive".into(),
        ..c.clone()
    };
    let query = surface(7).observe(&Observation::random(&grid, 1e5, true, &mut rng), 99);
    let twins = [7, 40];
    let mut db = LandmarkDatabase::new(&c);
    db.extend(landmarks).unwrap();
    let e = db.query(&query, &exhaustive).unwrap();
    assert_eq!(e.rejection, Some(Rejection::NotUnique), "{e:?}");
    // Unplaced: the short list of one never compares the twin.
    let r = db.query(&query, &c).unwrap();
    assert!(twins.contains(&r.candidate_index.unwrap()), "{r:?}");
    assert!(
        r.runner_up_index.is_none_or(|i| !twins.contains(&i)),
        "{r:?}"
    );
    // Placed, the twin 1 m away (within half an extent, 2.4 m): compared, and rejected as the
    // exhaustive matcher does.
    let all: Vec<usize> = (0..db.len()).collect();
    db.set_positions(&all, &at(1.0)).unwrap();
    let r = db.query(&query, &c).unwrap();
    assert_eq!(r.rejection, Some(Rejection::NotUnique), "{r:?}");
    assert!(
        r.runner_up_index.is_some_and(|i| twins.contains(&i)),
        "{r:?}"
    );
    // Placed 1.5 extents away: the signature speaks for it (not widened).
    db.set_positions(&all, &at(1.5 * extent)).unwrap();
    let r = db.query(&query, &c).unwrap();
    assert!(
        r.runner_up_index.is_none_or(|i| !twins.contains(&i)),
        "{r:?}"
    );
    // Positions are checked.
    assert!(db.set_positions(&[0], &[[f64::NAN, 0.0, 0.0]]).is_err());
    assert!(db.set_positions(&[41], &[[0.0; 3]]).is_err());
    assert!(db.set_positions(&[0, 1], &[[0.0; 3]]).is_err());
}

#[test]
fn keypoint_smoothing_starts_its_sums_where_an_iterator_sum_does() {
    // The row convolution replaced per-column `Iterator::sum`s; same bits need the same
    // start (-0.0 or +0.0 decides the sign of an all-zero sum).
    let empty: f64 = std::iter::empty::<f64>().sum();
    assert_eq!(empty.to_bits(), super::keypoints::SUM_START.to_bits());
}

#[test]
fn views_prepared_once_compare_and_query_like_fresh_ones() {
    // A run prepares each landmark once and shares it between the within-pass pairs, the
    // database and the queries: every result equals the one of the paths that prepare
    // their own (pairs under both headings and under one, coarse retrieval with 200 entries).
    // The views are prepared from landmarks whose cells wait on disk (`crate::spill`), as a
    // run's do: a view that read a cell from its head (empty there) would not compare alike.
    let c = cfg();
    let (db_landmarks, queries) = retrieval_set(Grid::tunnel(), 200, 20, 5);
    let all: Vec<Held> = db_landmarks
        .iter()
        .chain(&queries)
        .cloned()
        .map(Held::from)
        .collect();
    let dir = std::env::temp_dir().join(format!("decod-views-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let spill = crate::spill::Spill::create(&dir).unwrap();
    let on_disk: Vec<Held> = all
        .iter()
        .map(|h| spill.put(&h.landmark().unwrap()).unwrap())
        .collect();
    // Their patches wait there too, read back by each comparison.
    let views = prepare_views(&on_disk, &c, Some(&spill)).unwrap();
    let in_memory = prepare_views(&all[..1], &c, None).unwrap();
    assert!(views[0].heap_bytes() + 35_000 < in_memory[0].heap_bytes());
    let pairs: Vec<(usize, usize)> = (0..all.len() - 1)
        .map(|i| (i, (i * 7 + 3) % all.len()))
        .collect();
    for same_heading in [false, true] {
        assert_eq!(
            compare_view_pairs(&views, &pairs, &c, same_heading).unwrap(),
            compare_pairs(&all, &pairs, &c, same_heading).unwrap()
        );
    }
    assert!(compare_view_pairs(&views, &[(0, all.len())], &c, false).is_err());

    let n = db_landmarks.len();
    let ids: Vec<u64> = (0..n as u64).map(|k| k / 2).collect();
    let mut fresh = LandmarkDatabase::new(&c);
    fresh
        .extend_views(db_landmarks.clone(), ids.clone())
        .unwrap();
    let mut shared = LandmarkDatabase::new(&c);
    shared
        .extend_prepared(views[..n].to_vec(), ids.clone(), &c)
        .unwrap();
    let picked: Vec<&PreparedLandmark> = views[n..].iter().map(|v| &**v).collect();
    let got = shared
        .query_batch_prepared(&picked, None, &c, database::Eligibility::WithinRun)
        .unwrap();
    assert_eq!(got, fresh.query_batch(&queries, &c).unwrap());
    assert!(got.iter().filter(|r| r.accepted).count() >= 5);
    // Queries on disk, read back one at a time (a re-inspection's batch), find the same.
    let held = shared
        .query_batch_held(&on_disk[n..], &c, database::Eligibility::WithinRun)
        .unwrap();
    assert_eq!(held, got);
    // Under another config the entries are prepared again, from the cells on disk.
    let mut other = c.clone();
    other.max_keypoints += 1;
    let mut again = LandmarkDatabase::new(&c);
    again
        .extend_views(db_landmarks.clone(), ids.clone())
        .unwrap();
    let by = |db: &LandmarkDatabase| {
        db.query_batch_prepared(&picked, None, &other, database::Eligibility::WithinRun)
            .unwrap()
    };
    assert_eq!(by(&shared), by(&again));
    assert_eq!(shared.get(3).map(Held::on_disk), Some(true));
    // Views prepared under another config are refused, not stored.
    let mut db = LandmarkDatabase::new(&other);
    assert!(
        db.extend_prepared(views[..2].to_vec(), vec![0, 1], &c)
            .is_err()
    );
    assert!(db.is_empty());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn heading_prior_compares_only_the_heading_the_odometry_allows() {
    // A boundary revisited in the opposite direction: without directions both headings are
    // compared and the reversed one wins; with the axes antiparallel in the run's frame only
    // the reversed one is compared (same result); with them parallel (a prior that
    // contradicts the descriptors) only the forward one is, and nothing matches: the prior
    // decides which comparisons are made, not what they find. `heading_from_odometry = false`
    // ignores the directions.
    let mut c = cfg();
    let j = joint(1, 7);
    let mut db = LandmarkDatabase::new(&c);
    db.add(j.observe(&Observation::default(), 1)).unwrap();
    db.set_directions(&[0], &[[1.0, 0.0, 0.0]]).unwrap();
    let shape = patches::PatchShape::new(&c);
    let back = Observation {
        reversed: true,
        ..later(100.0)
    };
    let q = PreparedLandmark::new_query(Arc::new(j.observe(&back, 2)), &c, &shape).unwrap();
    let run = |c: &MatchingConfig, dir: Option<[f64; 3]>| {
        let d = dir.map(|d| vec![d]);
        db.query_batch_prepared(&[&q], d.as_deref(), c, database::Eligibility::WithinRun)
            .unwrap()
            .remove(0)
    };
    let both = run(&c, None);
    assert!(both.accepted, "{both:?}");
    assert_eq!(both.heading(), Heading::Reversed);
    let allowed = run(&c, Some([-0.9, 0.3, 0.0]));
    assert_eq!(allowed.pair, both.pair);
    let contradicted = run(&c, Some([0.9, -0.3, 0.0]));
    assert_eq!(contradicted.heading(), Heading::Forward);
    assert!(!contradicted.accepted, "{contradicted:?}");
    c.heading_from_odometry = false;
    // The database's own config still has the prior on: another config re-prepares.
    let off = run(&c, Some([0.9, -0.3, 0.0]));
    assert!(
        off.accepted && off.heading() == Heading::Reversed,
        "{off:?}"
    );
    // Bad directions are refused, naming the argument.
    let err = db.set_directions(&[0], &[[0.0; 3]]).unwrap_err();
    assert!(err.to_string().contains("directions"), "{err}");
    let err = db
        .query_batch_prepared(&[&q], Some(&[]), &c, database::Eligibility::WithinRun)
        .unwrap_err();
    assert!(err.to_string().contains("1 queries"), "{err}");
}

#[test]
fn a_views_patches_come_back_exactly_and_a_record_of_other_sizes_is_refused() {
    let c = cfg();
    let (landmarks, _) = retrieval_set(Grid::tunnel(), 1, 0, 3);
    let view = PreparedLandmark::new(landmarks[0].clone(), &c, &PatchShape::new(&c)).unwrap();
    let patches = view.patches().unwrap();
    let mut bytes = Vec::new();
    patches.encode(&mut bytes);
    let path = std::path::Path::new("views.spill");
    let back = patches::CandidatePatches::decode(&bytes, path).unwrap();
    let (mut a, mut b) = (Vec::new(), Vec::new());
    patches.encode(&mut a);
    back.encode(&mut b);
    assert_eq!(a, b);
    assert!(patches.count() > 0);
    for cut in [bytes.len() - 1, 11, 0] {
        match patches::CandidatePatches::decode(&bytes[..cut], path) {
            Err(DecodError::Database { path, .. }) => assert!(path.ends_with("views.spill")),
            other => panic!("expected a refusal naming the file, got {other:?}"),
        }
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(patches::CandidatePatches::decode(&longer, path).is_err());
}

#[test]
fn a_querys_flipped_mask_is_the_reversed_mask_on_any_grid() {
    // A view keeps its mask at heading 0 only; a query derives the flipped one. Grids whose
    // cell count is and is not a multiple of the 64 bits of a word.
    let mut rng = Rng::new(5);
    for (rows, cols) in [(16, 256), (5, 13), (1, 64), (3, 1)] {
        let mask: Vec<bool> = (0..rows * cols).map(|_| rng.normal() > 0.3).collect();
        let bits = bitset(mask.iter().copied());
        let expected = bitset(mask.iter().rev().copied());
        assert_eq!(flipped(&bits, (rows, cols)), expected, "{rows} x {cols}");
        assert_eq!(flipped(&flipped(&bits, (rows, cols)), (rows, cols)), bits);
    }
}
