//! Viewpoint recommendation on the paper's Cube, the tornado, real CT, and degenerate inputs;
//! progressive aggregation against the one-shot computation.

use neuvolex_bricks::BrickStore;

use neuvolex_classify::features::BrickFeatures;
use neuvolex_formats::MemVolume;
use neuvolex_tests::{shared, store_of};
use neuvolex_viewpoints::scores::{score_views, select, Aggregator, SelectConfig, Selection};
use neuvolex_viewpoints::{fibonacci_sphere, ClusterPartial, KMeans, KMeansConfig};

/// The whole pipeline on a store: k-means on `features` over the occupied bricks, partials
/// merged brick by brick in `order`, scores and selection.
fn recommend(
    store: &BrickStore,
    features: &str,
    k: usize,
    views: usize,
    reverse: bool,
) -> (Selection, Vec<[f32; 3]>, ClusterPartial, usize) {
    let fx = BrickFeatures::new(store, features.parse().unwrap(), None, false).unwrap();
    let mut bricks = store.occupied_bricks(None);
    let km = KMeans::fit(
        bricks.len(),
        fx.channels(),
        |i| Ok(fx.brick(&bricks[i]).unwrap()),
        &KMeansConfig {
            k,
            ..Default::default()
        },
    )
    .unwrap();
    if reverse {
        bricks.reverse();
    }
    let mut agg = Aggregator::new(k);
    for b in &bricks {
        let labels = km.assign(&fx.brick(b).unwrap());
        let g = store.derived(b).unwrap().gradient;
        agg.add(&ClusterPartial::from_brick(k, &labels, &g, store.info().spacing).unwrap());
    }
    let dirs = fibonacci_sphere(views);
    let summ = agg.partial().summary();
    let scores = score_views(&summ, &dirs).unwrap();
    let sel = select(&summ, &scores, &SelectConfig::default()).unwrap();
    let used = km.counts.iter().filter(|&&c| c > 0).count();
    (sel, dirs, agg.partial().clone(), used)
}

fn cube_store(n: usize) -> (tempfile::TempDir, BrickStore) {
    let (v, _) = neuvolex_bricks::synth::cube(n);
    store_of(&mut MemVolume::from_f32([n; 3], &v), 16)
}

#[test]
fn the_cube_gets_a_view_of_its_engraved_face_and_every_cluster_is_seen() {
    let (_d, store) = cube_store(48);
    let (sel, dirs, _, _) = recommend(&store, "local", 20, 1800, false);
    let face = neuvolex_bricks::synth::CUBE_ENGRAVED_NORMAL;
    let facing = sel.views.iter().any(|&i| {
        let d = dirs[i];
        d[0] as f64 * face[0] + d[1] as f64 * face[1] + d[2] as f64 * face[2] > 0.5
    });
    let picked: Vec<[f32; 3]> = sel.views.iter().map(|&i| dirs[i]).collect();
    assert!(
        facing,
        "no selected view faces the engraved face: {picked:?}"
    );
    assert!(
        sel.uncovered.is_empty(),
        "uncovered clusters {:?}",
        sel.uncovered
    );
    assert!(sel.views.len() <= 4, "a compact set: {picked:?}");
    // Seeded: the same again, and the same whichever order the bricks arrive in.
    let (again, _, p1, _) = recommend(&store, "local", 20, 1800, false);
    let (rev, _, p2, _) = recommend(&store, "local", 20, 1800, true);
    assert_eq!(sel, again);
    assert_eq!(
        p1, p2,
        "progressive aggregation in any order equals the one-shot sums"
    );
    assert_eq!(sel, rev);
}

#[test]
fn progressive_snapshots_converge_to_the_one_shot_scores() {
    let (_d, store) = cube_store(40);
    let (_, dirs, full, _) = recommend(&store, "local", 12, 400, false);
    // Merging the bricks one at a time: snapshots change, the last equals the one-shot.
    let one_shot = score_views(&full.summary(), &dirs).unwrap();
    let mut agg = Aggregator::new(12);
    let fx = BrickFeatures::new(&store, "local".parse().unwrap(), None, false).unwrap();
    let bricks = store.occupied_bricks(None);
    let km = KMeans::fit(
        bricks.len(),
        fx.channels(),
        |i| Ok(fx.brick(&bricks[i]).unwrap()),
        &KMeansConfig {
            k: 12,
            ..Default::default()
        },
    )
    .unwrap();
    let mut snaps = Vec::new();
    for b in &bricks {
        let labels = km.assign(&fx.brick(b).unwrap());
        let g = store.derived(b).unwrap().gradient;
        agg.add(&ClusterPartial::from_brick(12, &labels, &g, store.info().spacing).unwrap());
        snaps.push(agg.snapshot(&dirs).unwrap());
    }
    assert_eq!(snaps.last().unwrap(), &one_shot);
    assert_ne!(snaps[0], one_shot, "early snapshots are partial");
}

#[test]
fn degenerate_volumes_and_settings_give_clear_results_or_errors() {
    // A constant volume: no surfaces, so no view is better: a clear error.
    let (_d, store) = store_of(
        &mut MemVolume::from_f32([24; 3], &vec![3.0; 24 * 24 * 24]),
        16,
    );
    let fx = BrickFeatures::new(&store, "intensity".parse().unwrap(), None, false).unwrap();
    let bricks = store.bricks().collect::<Vec<_>>();
    let km = KMeans::fit(
        bricks.len(),
        1,
        |i| Ok(fx.brick(&bricks[i]).unwrap()),
        &KMeansConfig {
            k: 4,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(
        km.counts.iter().filter(|&&c| c > 0).count(),
        1,
        "one distinct feature"
    );
    let mut agg = Aggregator::new(4);
    for b in &bricks {
        let l = km.assign(&fx.brick(b).unwrap());
        let g = store.derived(b).unwrap().gradient;
        agg.add(&ClusterPartial::from_brick(4, &l, &g, [1.0; 3]).unwrap());
    }
    let summ = agg.partial().summary();
    let s = score_views(&summ, &fibonacci_sphere(10)).unwrap();
    let e = select(&summ, &s, &SelectConfig::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("constant"), "{e}");
    // k above the number of distinct features: the cube's intensity has two values.
    let (_d2, cube) = cube_store(32);
    let (sel, _, _, used) = recommend(&cube, "intensity", 10, 200, false);
    assert!(used <= 3, "{used} clusters used of 10");
    assert!(!sel.views.is_empty());
    // One candidate view: it is the answer.
    let (sel, _, _, _) = recommend(&cube, "local", 8, 1, false);
    assert_eq!(sel.views, vec![0]);
}

#[test]
fn the_tornado_and_real_ct_get_compact_view_sets() {
    let n = 48;
    let t = neuvolex_bricks::synth::tornado(n, 0.0);
    let (_d, store) = store_of(&mut MemVolume::from_f32([n; 3], &t), 16);
    let (sel, _, _, _) = recommend(&store, "local", 20, 600, false);
    assert!(!sel.views.is_empty() && sel.views.len() <= 12);
    assert!(sel.uncovered.is_empty(), "{:?}", sel.uncovered);
    let Some(ct) = shared("abdomen_ct/ct.nii.gz") else {
        return;
    };
    let mut src = neuvolex_bricks::open_volume(&ct, None).unwrap();
    let (_d, store) = store_of(&mut *src, 32);
    let (sel, dirs, _, used) = recommend(&store, "local", 50, 1800, false);
    eprintln!(
        "abdomen CT: {} views, {used} clusters used, first {:?}",
        sel.views.len(),
        dirs[sel.views[0]]
    );
    assert!(used > 40, "{used}");
    assert!(!sel.views.is_empty() && sel.views.len() <= 12);
    assert!(sel.coverage.iter().all(|c| c.is_finite()));
}

#[test]
fn the_viewpoint_stages_equal_the_single_process_pipeline_bit_for_bit() {
    use neuvolex_classify::pipeline::{FeatureSpec, OpenedFeatures};
    use neuvolex_viewpoints::distributed::recommend_on;
    use neuvolex_viewpoints::RecommendConfig;
    let (_d, store) = cube_store(48);
    let cfg = RecommendConfig {
        kmeans: KMeansConfig {
            k: 12,
            ..Default::default()
        },
        views: 600,
        ..Default::default()
    };
    // The single-process pipeline (k-means fit, then partials brick by brick).
    let fx = BrickFeatures::new(&store, "local".parse().unwrap(), None, false).unwrap();
    let bricks = store.occupied_bricks(None);
    let one = neuvolex_viewpoints::recommend(
        bricks.len(),
        fx.channels(),
        |i| Ok(fx.brick(&bricks[i]).unwrap()),
        |i| Ok(store.derived(&bricks[i]).unwrap().gradient),
        store.info().spacing,
        &cfg,
        &mut |_, _| {},
    )
    .unwrap();
    // The same as stages (sample, Lloyd passes, view partials) in tasks of 3 bricks.
    let set = "local".parse().unwrap();
    let src = OpenedFeatures {
        store: std::sync::Arc::new(BrickStore::open(store.root()).unwrap()),
        model: None,
        spec: FeatureSpec::new(store.root(), &set, false, None),
        set,
        model_bytes: None,
    };
    let mut events = 0;
    let (staged, run) = recommend_on(
        &neuvolex_tasks::LocalExecutor::new(),
        src,
        &cfg,
        3,
        &mut |_| events += 1,
        &mut |_, _| {},
    )
    .unwrap();
    assert_eq!(
        staged.kmeans, one.kmeans,
        "centroids, inertia, counts, iterations"
    );
    assert_eq!(staged.summary, one.summary);
    assert_eq!(staged.scores, one.scores);
    assert_eq!(staged.selection, one.selection);
    assert!(run.tasks > 0 && run.dead.is_empty() && events > 0);
}
