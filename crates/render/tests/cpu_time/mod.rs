//! Process CPU time for the render crate's benchmarks, examples and measurement tests (shared
//! with `#[path]` includes): on a shared machine CPU seconds are steadier than wall time.

/// CPU seconds (user + system) this process has used so far, from `/proc/self/stat` (Linux;
/// NaN elsewhere). utime and stime are fields 14 and 15, i.e. 11 and 12 after the
/// parenthesised command name; USER_HZ is 100 on Linux.
pub fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    let Some(close) = stat.rfind(')') else {
        return f64::NAN;
    };
    let f: Vec<&str> = stat[close + 2..].split_whitespace().collect();
    let tick = |i: usize| {
        f.get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (tick(11) + tick(12)) / 100.0
}
