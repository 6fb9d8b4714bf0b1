//! The image does not depend on which cache slot a brick landed in. Bricks reach the GPU in the
//! order they arrive (from disk, from a server, after an outage, under another budget), so the
//! same cut sits in different slots from run to run; with exact trilinear the weights come from
//! the in-slot coordinate alone (field.wgsl `fetch`), and two such runs must agree bit for bit.
use crate::common;
use common::*;
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;

/// Level-1 nodes in a 3D checkerboard, level 0 elsewhere: fine and coarse nodes, transition
/// bands across faces, edges and corners (the coarse neighbour's slot matters there too).
fn checker_levels(p: [u32; 3]) -> u8 {
    ((p[0] >> 1) + (p[1] >> 1) + (p[2] >> 1)).is_multiple_of(2) as u8
}

/// The same cut with every slot moved: slot s becomes n - 1 - s, so each brick sits at another
/// place of the cache texture (other texel coordinates, other magnitudes).
fn with_slots_reversed(table: &PageTable) -> PageTable {
    let slot_count = BrickedVolume::resident_nodes(table).len() as u32;
    let mut moved = table.clone();
    for entry in moved.entries.iter_mut().filter(|e| e.resident) {
        entry.slot_in_cache = slot_count - 1 - entry.slot_in_cache;
    }
    moved
}

#[test]
fn images_do_not_depend_on_cache_slots_with_exact_trilinear() {
    let ctx = gpu();
    let phantom_128 = || {
        phantom::ct_phantom(VolumeGeometry::axis_aligned([128; 3], [1.0; 3]), None, None).unwrap()
    };
    let volume = phantom_128();
    let table = volume.page_table_with_levels(checker_levels);
    let moved = with_slots_reversed(&table);
    assert_ne!(table.entries, moved.entries, "the slots did not move");
    let first = Fixture::new(volume, table, test_tf());
    let second = Fixture::new(phantom_128(), moved, test_tf());
    let mut first_scene = GpuScene::new(&ctx, &first, CacheConfig::default());
    let mut second_scene = GpuScene::new(&ctx, &second, CacheConfig::default());
    let cam = orbit(&first.volume.geometry, 35.0, 25.0, 1.5, 35.0);
    let cases = [
        ("dvr", RenderMode::Dvr, None),
        ("dvr-shaded", RenderMode::Dvr, Some(Shading::default())),
        ("mip", RenderMode::Mip, None),
        ("iso", RenderMode::Isosurface, Some(Shading::default())),
    ];
    for (name, mode, shading) in cases {
        let settings = RenderSettings {
            shading,
            iso_value: 300.0,
            exact_trilinear: true,
            ..compare_settings(mode, SIZE)
        };
        assert!(settings.smooth_transitions);
        let a = first_scene.render(&ctx, &first, &cam, &settings);
        let b = second_scene.render(&ctx, &second, &cam, &settings);
        assert!(
            a.rgba.iter().any(|&v| v > 0),
            "{name}: the image is empty, the comparison would prove nothing"
        );
        let differing = a.rgba.iter().zip(&b.rgba).filter(|(x, y)| x != y).count();
        assert_eq!(
            differing, 0,
            "{name}: {differing} channels change when the bricks sit in other slots"
        );
    }
}
