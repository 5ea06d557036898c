//! End-to-end matcher tests on synthetic descriptors (`synthetic.rs`).

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

#[test]
fn same_boundary_twice_matches() {
    let j = joint(1, 1);
    let a = j.observe(&Observation::default(), 1);
    let b = j.observe(&Observation { stamp: 100.0, ..Observation::default() }, 2);
    let r = compare(&a, &b, &cfg()).unwrap();
    eprintln!("{r:?}");
    assert_eq!(r.heading, Heading::Forward);
    assert!(r.inliers >= cfg().min_inliers, "{r:?}");
    assert!(r.rejection.is_none());
}
