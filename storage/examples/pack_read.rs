//! `cargo run --example pack_read -p strata-storage -- STORE [PASSES]`: format 3's two possible
//! read paths for brick records, side by side on one store (issue 48): a slice of the pack's
//! memory map (what `Store` does) against `pread` into a buffer (one syscall and one copy per
//! record). Each pass reads every record once and checks its checksum (`verify_record`, what
//! every read does before decoding), in pack order and in a shuffled order (a viewer's reads),
//! alternating the two paths so that both see the same page cache. Prints the median per path.

use std::collections::HashMap;
use std::os::unix::fs::FileExt;
use std::path::PathBuf;
use std::time::Instant;

use strata_storage::brick::verify_record;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args_os().skip(1);
    let path = PathBuf::from(args.next().ok_or("usage: pack_read STORE [PASSES]")?);
    let passes: usize = args
        .next()
        .and_then(|p| p.to_str()?.parse().ok())
        .unwrap_or(5);
    let store = strata_storage::Store::open(&path)?;
    let records = store.record_locations();
    if records.is_empty() {
        return Err("not a format-3 store (no pack records)".into());
    }
    let files: HashMap<PathBuf, std::fs::File> = records
        .iter()
        .map(|r| Ok((r.2.clone(), std::fs::File::open(&r.2)?)))
        .collect::<std::io::Result<_>>()?;
    let bytes: u64 = records.iter().map(|r| u64::from(r.4)).sum();
    let mut pack_order: Vec<usize> = (0..records.len()).collect();
    pack_order.sort_by_key(|&i| (&records[i].2, records[i].3));
    let mut shuffled = pack_order.clone();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for i in (1..shuffled.len()).rev() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        shuffled.swap(i, (state % (i as u64 + 1)) as usize);
    }
    let mut buffer = Vec::new();
    let mut pread = |order: &[usize]| -> Result<f64, Box<dyn std::error::Error>> {
        let started = Instant::now();
        for &i in order {
            let (_, id, pack, offset, len) = &records[i];
            buffer.resize(*len as usize, 0);
            files[pack].read_exact_at(&mut buffer, *offset)?;
            verify_record(*id, &buffer).map_err(|e| format!("{id:?}: {e:?}"))?;
        }
        Ok(started.elapsed().as_secs_f64())
    };
    let mapped = |order: &[usize]| -> Result<f64, Box<dyn std::error::Error>> {
        let started = Instant::now();
        for &i in order {
            let (frame, id, ..) = &records[i];
            let record = if *frame == 0 {
                store.brick_record(*id)?
            } else {
                std::borrow::Cow::Owned(store.read_frame_brick_record(*frame, *id)?)
            };
            verify_record(*id, &record).map_err(|e| format!("{id:?}: {e:?}"))?;
        }
        Ok(started.elapsed().as_secs_f64())
    };
    // One untimed pass of each warms the page cache and the maps' page tables alike.
    pread(&pack_order)?;
    mapped(&pack_order)?;
    println!(
        "{}: {} records, {:.1} MB, {passes} passes per path and order (warm page cache)",
        path.display(),
        records.len(),
        bytes as f64 / 1e6
    );
    for (name, order) in [("pack order", &pack_order), ("shuffled", &shuffled)] {
        let (mut m, mut p) = (Vec::new(), Vec::new());
        for _ in 0..passes {
            m.push(mapped(order)?);
            p.push(pread(order)?);
        }
        let (m, p) = (median(&mut m), median(&mut p));
        let per = |s: f64| s * 1e6 / records.len() as f64;
        println!(
            "  {name}: mmap {:.3} s ({:.0} MB/s, {:.2} µs a record), pread {:.3} s ({:.0} MB/s, {:.2} µs a record): pread/mmap time {:.2}",
            m,
            bytes as f64 / 1e6 / m,
            per(m),
            p,
            bytes as f64 / 1e6 / p,
            per(p),
            p / m
        );
    }
    Ok(())
}
