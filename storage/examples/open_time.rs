//! `cargo run --example open_time -p strata-storage -- STORE`: how long `Store::open` takes and
//! what the skeleton costs (encoded bytes as stored, memory, nodes kept) against the dense
//! encoding of earlier builds (5 bytes per node of every level).

use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path = std::env::args_os().nth(1).ok_or("usage: open_time STORE")?;
    let started = Instant::now();
    let store = strata_storage::Store::open(std::path::Path::new(&path))?;
    let open = started.elapsed();
    let skeleton = store.skeleton();
    let layout = store.layout();
    println!(
        "open {:.3} s; skeleton {} B encoded, {} B in memory, {} of {} nodes kept; dense encoding would be {} B",
        open.as_secs_f64(),
        skeleton.encode().len(),
        skeleton.memory_bytes(),
        skeleton.stored_nodes(),
        layout.total_bricks(),
        4 + layout.level_count() as u64 * 8 + layout.total_bricks() * 5 + 8
    );
    Ok(())
}
