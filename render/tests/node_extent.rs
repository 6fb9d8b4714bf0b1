//! Node-extent exit (raycast.wgsl `NODE_EXTENT`, page_table.rs `FLAG_WHOLE_NODE` and skip
//! levels): on a cut with coarse leaves, a parent standing in for some of its children and a
//! not-resident region, rays read fewer page-table words than the cell-by-cell march (the same
//! shader built with `const NODE_EXTENT: bool = false;`), sample the same points and make the
//! same images, which match the f64 reference.
use crate::common;
use common::*;
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;

/// The shader as it was before the node-extent exit: every cell read, every skip one cell.
fn cell_by_cell_source() -> String {
    let source = Raycaster::shader_source();
    let variant = source.replace(
        "const NODE_EXTENT: bool = true;",
        "const NODE_EXTENT: bool = false;",
    );
    assert_ne!(
        variant, source,
        "NODE_EXTENT switch not found in raycast.wgsl"
    );
    variant
}

/// 256³ phantom, 8³ pages: level 2 for x ≥ 4 (coarse leaves, some all air), level 1 for y ≥ 4,
/// level 0 elsewhere except page (1, 1, 1), which shows its level-1 parent (the loader's
/// pending child: a node whose other cells hold level-0 leaves); pages z = 7, x < 4 not
/// resident (culled).
fn mixed_cut_fixture() -> Fixture {
    let volume = phantom::ct_phantom(
        VolumeGeometry::axis_aligned([256; 3], [1.0; 3]),
        None,
        Some(80.0),
    )
    .unwrap();
    let mut table = volume.page_table_with_levels(|p| {
        if p[0] >= 4 {
            2
        } else if p[1] >= 4 || p == [1, 1, 1] {
            1
        } else {
            0
        }
    });
    for i in 0..table.entries.len() {
        let p = table.page_of_linear(i);
        if p[2] == 7 && p[0] < 4 {
            table.entries[i] = PageEntry::NOT_RESIDENT;
        }
    }
    Fixture::new(volume, table, test_tf())
}

fn cameras(f: &Fixture) -> Vec<(&'static str, Camera)> {
    let g = &f.volume.geometry;
    let centre = g.centre_patient();
    vec![
        ("oblique", orbit(g, 35.0, 25.0, 1.5, 35.0)),
        (
            // Orthographic rays along an index axis, on the page faces' planes where they
            // graze the cells' boundaries.
            "axis",
            Camera::look_at(
                [centre.x, centre.y, centre.z - 600.0],
                [centre.x, centre.y, centre.z],
                [0.0, -1.0, 0.0],
                Projection::Orthographic { height_mm: 300.0 },
            ),
        ),
        (
            "inside",
            Camera::look_at(
                [centre.x + 90.0, centre.y - 70.0, centre.z + 40.0],
                [centre.x - 50.0, centre.y + 30.0, centre.z - 20.0],
                [0.0, 0.0, 1.0],
                Projection::Perspective { fov_y_deg: 60.0 },
            ),
        ),
    ]
}

#[test]
fn node_extent_exit_reads_fewer_entries_and_keeps_every_image() {
    let ctx = gpu();
    let f = mixed_cut_fixture();
    let whole = f.page_table.whole_node_flags();
    let parent = f.page_table.linear([1, 1, 1]);
    assert!(
        !whole[parent],
        "the stand-in parent must not count as a whole node"
    );
    assert!(whole[f.page_table.linear([5, 5, 5])]);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let mut before = Raycaster::with_shader_source(&ctx, &g.cache, &cell_by_cell_source());
    let modes = [
        ("dvr", RenderMode::Dvr, None),
        ("dvr-shaded", RenderMode::Dvr, Some(Shading::default())),
        ("mip", RenderMode::Mip, None),
        ("iso", RenderMode::Isosurface, Some(Shading::default())),
    ];
    let (mut reads_before, mut reads_after) = (0u64, 0u64);
    for (view, cam) in cameras(&f) {
        for (name, mode, shading) in modes {
            let s = RenderSettings {
                shading,
                iso_value: 300.0,
                ..compare_settings(mode, SIZE)
            };
            assert!(s.smooth_transitions && s.skip_empty);
            let after = g.render(&ctx, &f, &cam, &s);
            let scene = FrameInputs {
                cache: &g.cache,
                page_table: &g.page_table,
                transfer_function: &g.tf,
                geometry: &f.volume.geometry,
                mapping: f.volume.mapping,
                camera: &cam,
                settings: &s,
            };
            let old = before.render_blocking(&ctx, &scene).unwrap();
            let c = compare_rgba8(&old.rgba, &after.rgba).unwrap();
            let (rb, ra) = (old.page_reads.unwrap(), after.page_reads.unwrap());
            let pixels = (SIZE * SIZE) as f64;
            eprintln!(
                "{view}/{name}: page reads per pixel {:.2} -> {:.2} ({:.2}x fewer), samples {:?} -> {:?}, image {c:?}",
                rb as f64 / pixels,
                ra as f64 / pixels,
                rb as f64 / ra.max(1) as f64,
                old.samples,
                after.samples
            );
            // Same lattice, same skipped regions, same words for the same cells: the images
            // are the same. The one freedom is a probe within f32 rounding of a cell face,
            // which the two marches may attribute to different cells of equal payload (the
            // apron), so a sample count may differ by a handful and a pixel by 1/255.
            assert!(c.max_abs_error <= 1, "{view}/{name}: {c:?}");
            assert!(c.pixels_off_by_more_than_one == 0, "{view}/{name}: {c:?}");
            let (sb, sa) = (old.samples.unwrap() as i64, after.samples.unwrap() as i64);
            assert!(
                (sb - sa).abs() * 1000 <= sb.max(1),
                "{view}/{name}: samples {sb} vs {sa}"
            );
            assert!(ra <= rb, "{view}/{name}: more page reads {rb} -> {ra}");
            reads_before += rb;
            reads_after += ra;
        }
    }
    // The cut is mostly coarse leaves and not-resident blocks: a real saving, not noise.
    assert!(
        reads_after * 3 <= reads_before * 2,
        "page reads {reads_before} -> {reads_after}: less than a third saved"
    );
}

#[test]
fn node_extent_exit_matches_the_reference_on_the_mixed_cut() {
    let ctx = gpu();
    let f = mixed_cut_fixture();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    // Closer than the first test's view, so the isosurface covers enough pixels to prove
    // something.
    let cam = orbit(&f.volume.geometry, 35.0, 25.0, 2.5, 35.0);
    // Same bars as gpu_vs_reference.rs and smooth_transitions.rs: lavapipe's sampler uses
    // 8-bit trilinear weights, which the 40 dB / 24 max bar absorbs; isosurface silhouettes
    // are opaque, so the max is free there and the count of such pixels bounded.
    for (name, mode, max_abs) in [
        ("node-extent-dvr", RenderMode::Dvr, 24u8),
        ("node-extent-mip", RenderMode::Mip, 24),
        ("node-extent-iso", RenderMode::Isosurface, 255),
    ] {
        let s = RenderSettings {
            iso_value: 300.0,
            shading: (mode != RenderMode::Mip).then(Shading::default),
            ..compare_settings(mode, SIZE)
        };
        let frame = g.render(&ctx, &f, &cam, &s);
        let reference = f.reference(&cam, &s, 8.0);
        let c = assert_close(name, &frame, &reference, 40.0, max_abs);
        if mode == RenderMode::Isosurface {
            assert!(
                c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
                "{name}: more than 1% of pixels off: {c:?}"
            );
        }
    }
}

#[test]
fn lean_mip_march_makes_the_general_marchs_images() {
    let ctx = gpu();
    let f = mixed_cut_fixture();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let general_source = Raycaster::shader_source().replace(
        "const LEAN_MIP: bool = true;",
        "const LEAN_MIP: bool = false;",
    );
    assert_ne!(
        general_source,
        Raycaster::shader_source(),
        "LEAN_MIP switch not found"
    );
    let mut general = Raycaster::with_shader_source(&ctx, &g.cache, &general_source);
    for (view, cam) in cameras(&f) {
        for skip_empty in [true, false] {
            let s = RenderSettings {
                skip_empty,
                ..compare_settings(RenderMode::Mip, SIZE)
            };
            let lean = g.render(&ctx, &f, &cam, &s);
            let scene = FrameInputs {
                cache: &g.cache,
                page_table: &g.page_table,
                transfer_function: &g.tf,
                geometry: &f.volume.geometry,
                mapping: f.volume.mapping,
                camera: &cam,
                settings: &s,
            };
            let old = general.render_blocking(&ctx, &scene).unwrap();
            eprintln!(
                "{view}/skip {skip_empty}: samples {:?} -> {:?}, page reads {:?} -> {:?}",
                old.samples, lean.samples, old.page_reads, lean.page_reads
            );
            // The same samples at the same points in the same order, the same maximum: the
            // same bytes, depths and visibility marks.
            assert_eq!(old.rgba, lean.rgba, "{view}/skip {skip_empty}");
            assert_eq!(old.depth, lean.depth, "{view}/skip {skip_empty}");
            assert_eq!(old.visibility, lean.visibility, "{view}/skip {skip_empty}");
            assert_eq!(old.samples, lean.samples, "{view}/skip {skip_empty}");
        }
    }
}
