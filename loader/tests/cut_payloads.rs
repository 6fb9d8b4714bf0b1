//! The cut's payloads for a CPU pass beside the raycaster (the viewer's adaptive oracle): the
//! root, read at open straight onto the GPU, is taken from the volume's own copy; a node the
//! CPU cache no longer holds is read from the store by `read_missing`; every resident node of a
//! converged cut is there with the store's voxels; the residency generation moves with the
//! cut and stays put once it converged.

use crate::common;

use common::*;
use strata_loader::StreamingConfig;
use strata_render::{BrickSource, PageTable};
use strata_source::VolumeSource;
use strata_types::BrickId;

#[test]
fn the_converged_cuts_payloads_are_the_stores_bricks_and_the_generation_follows_the_cut() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let camera = orbit(&store, 30.0, 20.0, 1.0);
    let config = StreamingConfig {
        max_voxel_pixels: 0.25,
        ..config()
    };
    let mut volume = stream(&ctx, &store, &tf, config);
    assert_eq!(volume.residency_generation(), 0);
    // Before the first frame the cut is the root, read at open straight onto the GPU: the
    // snapshot takes the volume's own copy of it (the page, which cannot read on another
    // thread, builds its oracle from the snapshot alone), so nothing is missing and there is
    // nothing to read.
    let mut root_only = volume.cut_payloads();
    assert_eq!((root_only.len(), root_only.missing()), (1, 0));
    assert!(root_only.read_missing(|| true).unwrap());
    let root = BrickId::new((store.layout().level_count() - 1) as u8, [0, 0, 0]);
    assert_eq!(
        root_only.brick(root.level, root.coords),
        Some(
            VolumeSource::read_brick(store.as_ref(), root)
                .unwrap()
                .as_slice()
        )
    );
    converge(&ctx, &mut volume, &camera, &s, 300);
    let generation = volume.residency_generation();
    assert!(generation > 0, "the cut refined, so bricks were uploaded");
    // A converged, unchanged view uploads nothing and keeps its table.
    let stats = volume.frame(&ctx, &camera, &s).unwrap();
    assert!(stats.converged);
    assert_eq!(volume.residency_generation(), generation);

    let table = volume.page_table().to_page_table();
    let mut nodes: Vec<BrickId> = table
        .entries
        .iter()
        .enumerate()
        .filter(|(_, e)| e.resident)
        .map(|(i, e)| {
            BrickId::new(
                e.level,
                PageTable::node_of(table.page_of_linear(i), e.level),
            )
        })
        .collect();
    nodes.sort_unstable();
    nodes.dedup();
    assert!(nodes.len() > 1, "a refined cut has more than the root");

    let mut payloads = volume.cut_payloads();
    assert_eq!(payloads.len() + payloads.missing(), nodes.len());
    assert!(payloads.read_missing(|| false).unwrap());
    assert_eq!(payloads.missing(), 0);
    assert_eq!(payloads.len(), nodes.len());
    for id in nodes {
        let expected = VolumeSource::read_brick(store.as_ref(), id).unwrap();
        assert_eq!(
            payloads.brick(id.level, id.coords),
            Some(expected.as_slice()),
            "{id:?}"
        );
    }
}
