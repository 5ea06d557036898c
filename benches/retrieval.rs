//! `cargo bench --bench retrieval`: a query against 100 to 10,000 prepared landmarks with the
//! coarse short list (`matching.retrieval = "coarse"`) and, for reference, exhaustively; the
//! coarse stage alone up to 100,000 signatures. Throughput is in landmarks per second
//! (elements = database size). Target on two cores (DESIGN.md, issue 12): a query against
//! 10,000 landmarks <= 5 ms. The memory per landmark is printed once (prepared data:
//! descriptor, patches, masks, signatures).
//!
//! The 10,000-landmark database repeats 2,000 distinct synthetic joints (views of one joint
//! differ by noise and misalignment); the timing depends on the database size and the
//! short-list length, not on what the entries hold. Entries are placed as a tunnel's rings
//! (`matching.retrieval_neighbour_extents`): one boundary per distinct joint, 1.5 m apart,
//! its views within centimetres, so the short list is widened by the views of the rings
//! beside its best as it is on a real survey. 100,000 prepared landmarks would take
//! ~12.5 GB (see the printed bytes per landmark), so the largest size runs the coarse stage
//! (the part that grows with the database) on its own.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use decod::DecodConfig;
use decod::landmark::Landmark;
use decod::matching::LandmarkDatabase;
use decod::matching::retrieval::{CoarseIndex, QuantisedQuery, signature_len};
use decod::matching::synthetic::{Grid, JointSurface, Observation, Rng, SurfaceParams};

const DISTINCT: usize = 2000;
/// Ring spacing of the placed database, metres (the segmental tunnel of the matrix).
const RING_M: f64 = 1.5;

/// Where entry `k` of [`landmarks`] lies: its joint's ring, views 1 cm apart.
fn position(k: usize) -> [f64; 3] {
    [
        RING_M * (k % DISTINCT) as f64 + 0.01 * (k / DISTINCT) as f64,
        0.0,
        0.0,
    ]
}

/// `n` landmarks: `DISTINCT` synthetic views, then copies of them at other stamps.
fn landmarks(n: usize, seed: u64) -> Vec<Landmark> {
    let g = Grid::tunnel();
    let mut rng = Rng::new(seed);
    let distinct: Vec<Landmark> = (0..DISTINCT.min(n))
        .map(|k| {
            let joint = JointSurface::new(g, SurfaceParams::for_grid(&g), 1, k as u64);
            joint.observe(
                &Observation::random(&g, 10.0 * k as f64, false, &mut rng),
                k as u64,
            )
        })
        .collect();
    (0..n)
        .map(|k| {
            let mut l = distinct[k % distinct.len()].clone();
            l.submap_stamp = 10.0 * k as f64;
            l.scan_stamps = vec![l.submap_stamp];
            l
        })
        .collect()
}

fn query_of(k: u64) -> Landmark {
    let g = Grid::tunnel();
    let mut rng = Rng::new(99);
    let joint = JointSurface::new(g, SurfaceParams::for_grid(&g), 1, k);
    joint.observe(&Observation::random(&g, 1.0e6, true, &mut rng), 12345)
}

fn bench(c: &mut Criterion) {
    let base = DecodConfig::tunnel().matching;
    let mut coarse = base.clone();
    coarse.retrieval = "coarse".into();
    coarse.retrieval_min_candidates = 0;
    let mut exhaustive = base.clone();
    exhaustive.retrieval = "exhaustive".into();
    let all = landmarks(10_000, 7);
    let query = query_of(3);

    let mut group = c.benchmark_group("retrieval");
    for n in [100usize, 1000, 10_000] {
        let mut db = LandmarkDatabase::new(&base);
        let indices: Vec<usize> = (0..n).collect();
        let placed: Vec<[f64; 3]> = indices.iter().map(|&k| position(k)).collect();
        if db.extend(all[..n].to_vec()).is_err() || db.set_positions(&indices, &placed).is_err() {
            return;
        }
        if n == 10_000 {
            eprintln!("memory per landmark: {} bytes", db.bytes_per_landmark());
        }
        group.throughput(Throughput::Elements(n as u64));
        group.bench_function(format!("query_coarse_{n}"), |b| {
            b.iter(|| db.query(black_box(&query), &coarse))
        });
        if n <= 1000 {
            group.bench_function(format!("query_exhaustive_{n}"), |b| {
                b.iter(|| db.query(black_box(&query), &exhaustive))
            });
        }
    }
    // The coarse stage alone (the part linear in the database), up to 100,000 signatures.
    let g = Grid::tunnel();
    let dim = signature_len(g.rows, g.cols);
    let mut rng = Rng::new(3);
    let mut row = || -> Vec<f32> { (0..dim).map(|_| rng.normal() as f32 * 0.03).collect() };
    // Quantised once, as a prepared view keeps it.
    let q = QuantisedQuery::new(&[row(), row(), row(), row(), row(), row()]);
    let mut index = CoarseIndex::default();
    for _ in 0..100_000 {
        index.push(&row());
    }
    for n in [100usize, 1000, 10_000, 100_000] {
        let indices: Vec<usize> = (0..n).collect();
        group.throughput(Throughput::Elements(n as u64));
        group.bench_function(format!("coarse_stage_{n}"), |b| {
            b.iter(|| index.short_list(black_box(&q), &indices, 48, true))
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
