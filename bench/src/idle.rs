//! `strata-bench idle`: the viewer's CPU at rest (issue 36). Starts `strata view` as a child
//! (unsupervised, so the child is the window), lets it settle with the pointer outside the
//! window, then reads the child's CPU time (all its threads, /proc/PID/stat) over a settled
//! interval, and from its frame log how many UI passes and volume frames it drew meanwhile.
//! Needs a display: run under `xvfb-run -a` where there is none.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

#[derive(clap::Args)]
pub struct Options {
    /// What `strata view` opens (store, scan or URL); the demo phantom without it.
    pub path: Option<PathBuf>,
    /// Seconds to let the view open and converge before measuring.
    #[arg(long, default_value_t = 30.0)]
    pub settle: f64,
    /// Length of the settled interval measured, seconds.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Window size WxH in points, passed to `strata view`.
    #[arg(long, default_value = "1360x860")]
    pub window: String,
    /// Extra arguments for `strata view` (e.g. --layout=single), one per flag.
    #[arg(long = "view-arg", allow_hyphen_values = true)]
    pub view_args: Vec<String>,
}

pub fn run(options: Options) -> Result<()> {
    if std::env::var_os("DISPLAY").is_none() && std::env::var_os("WAYLAND_DISPLAY").is_none() {
        bail!("no display: run it under Xvfb, e.g. `xvfb-run -a strata-bench idle`");
    }
    let exe = crate::strata_exe()?;
    let scratch = tempfile::tempdir().context("a scratch folder for the frame log")?;
    let log = scratch.path().join("frames.csv");
    let total = options.settle + options.seconds;
    let mut command = Command::new(exe);
    command.arg("view");
    if let Some(path) = &options.path {
        command.arg(path);
    }
    command
        .args(["--fresh", "--window", &options.window])
        .arg("--exit-after")
        .arg(format!("{:.1}", total + 1.0))
        .arg("--frame-log")
        .arg(&log)
        .args(&options.view_args)
        .env("STRATA_NO_SUPERVISOR", "1")
        .stdin(Stdio::null());
    let started = Instant::now();
    let mut child = command.spawn().context("starting strata view")?;
    let pid = child.id();
    let wait_until = |seconds: f64| {
        let left = Duration::from_secs_f64(seconds).saturating_sub(started.elapsed());
        std::thread::sleep(left);
    };
    wait_until(options.settle);
    let before = cpu_seconds(pid)?;
    let t0 = started.elapsed().as_secs_f64();
    wait_until(total);
    let after = cpu_seconds(pid)?;
    let t1 = started.elapsed().as_secs_f64();
    let status = child.wait().context("waiting for strata view")?;
    if !status.success() {
        bail!("strata view exited with {status}");
    }
    let cpu_percent = (after - before) / (t1 - t0) * 100.0;
    println!(
        "idle CPU over {:.1} s settled (after {:.0} s): {cpu_percent:.1} % of a core",
        t1 - t0,
        options.settle
    );
    let text = std::fs::read_to_string(&log)
        .with_context(|| format!("reading the frame log {}", log.display()))?;
    let (ui_passes, volume_frames) = frames_between(&text, t0, t1);
    println!("UI passes in the interval: {ui_passes}; volume frames: {volume_frames}");
    Ok(())
}

/// User + system CPU seconds of process `pid`, all threads (/proc/PID/stat fields 14 and 15,
/// in USER_HZ ticks).
fn cpu_seconds(pid: u32) -> Result<f64> {
    let path = format!("/proc/{pid}/stat");
    let stat = std::fs::read_to_string(&path)
        .with_context(|| format!("reading {path} (did strata view exit early?)"))?;
    parse_cpu_seconds(&stat, ticks_per_second()).with_context(|| format!("parsing {path}"))
}

#[cfg(unix)]
fn ticks_per_second() -> f64 {
    // SAFETY: sysconf reads a constant of the running system and has no preconditions.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if ticks > 0 {
        ticks as f64
    } else {
        100.0
    }
}

#[cfg(not(unix))]
fn ticks_per_second() -> f64 {
    // /proc is Linux's; elsewhere `cpu_seconds` fails before this matters.
    100.0
}

fn parse_cpu_seconds(stat: &str, ticks_per_second: f64) -> Result<f64> {
    // The command name (field 2) is in parentheses and may hold spaces: count after its end.
    let rest = stat
        .rfind(')')
        .map(|end| &stat[end + 1..])
        .context("no ')' after the command name")?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // `rest` starts at field 3 (state): utime is field 14, stime field 15.
    let field = |n: usize| -> Result<f64> {
        let text = fields.get(n - 3).context("too few fields")?;
        text.parse::<f64>()
            .with_context(|| format!("field {n} is not a number: {text}"))
    };
    Ok((field(14)? + field(15)?) / ticks_per_second)
}

/// UI passes logged with `t0 < seconds <= t1`, and the volume frames drawn between the last
/// pass at or before `t0` and the last at or before `t1` (the log's counter is cumulative).
fn frames_between(csv: &str, t0: f64, t1: f64) -> (usize, u64) {
    let rows: Vec<(f64, u64)> = csv
        .lines()
        .skip(1)
        .filter_map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            Some((cells.first()?.parse().ok()?, cells.get(3)?.parse().ok()?))
        })
        .collect();
    let counter_at = |t: f64| {
        rows.iter()
            .rev()
            .find(|(s, _)| *s <= t)
            .map_or(0, |(_, v)| *v)
    };
    let passes = rows.iter().filter(|(s, _)| *s > t0 && *s <= t1).count();
    (passes, counter_at(t1).saturating_sub(counter_at(t0)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_is_read_after_a_command_name_with_spaces_and_parentheses() {
        let stat = "4242 (strata (view) x) S 1 2 3 4 5 6 7 8 9 10 250 50 0 0 20 0 12";
        let seconds = parse_cpu_seconds(stat, 100.0).expect("parses");
        assert!((seconds - 3.0).abs() < 1e-12, "{seconds}");
        assert!(parse_cpu_seconds("4242 strata S 1", 100.0).is_err());
    }

    #[test]
    fn frames_are_counted_inside_the_interval_only() {
        let csv = "seconds,ui_interval_ms,ui_cpu_ms,volume_frames\n\
                   1.0,16,1,10\n5.0,16,1,40\n12.0,16,1,41\n16.0,16,1,45\n";
        assert_eq!(frames_between(csv, 5.0, 15.0), (1, 1));
        assert_eq!(frames_between(csv, 0.0, 20.0), (4, 45));
    }
}
