//! Mutation fuzzing of the log readers and message decoders (issue 11), run for minutes as a
//! benchmark, never in CI:
//!
//! ```text
//! cargo run --release --example fuzz_logs -- SECONDS SEED_LOG...
//! ```
//!
//! Each input is one seed log (`.mcap`, `.bag`, `.db3`) mutated a few times (bytes flipped,
//! a length field set to an extreme value, a range zeroed, duplicated or cut off), written to
//! a scratch file and read to the end with [`MessageSource`]; every message of a type decod
//! reads is decoded, and decoded once more after its own mutation. A panic is caught and
//! counted (the run fails); the slowest input is reported, so a hang would show. Prints the
//! number of inputs tried. Seeds: any logs, e.g. those `tests/test_real_logs.py` builds.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use decod::io::log::container_of;
use decod::io::messages::{MessageKind, decode_cloud, decode_imu_message, decode_poses};
use decod::io::source::MessageSource;
use decod::io::wire::Encoding;

/// xorshift64*: enough randomness for mutations, no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One to eight mutations of `data` in place.
fn mutate(rng: &mut Rng, data: &mut Vec<u8>) {
    for _ in 0..1 + rng.below(8) {
        if data.is_empty() {
            return;
        }
        let at = rng.below(data.len());
        match rng.below(6) {
            0 => data[at] ^= 1 << rng.below(8),
            1 => data[at] = rng.next() as u8,
            2 => {
                // A length-like field set to an extreme value.
                let value = [0u64, 1, u64::from(u32::MAX), u64::MAX, rng.next()][rng.below(5)];
                let end = (at + 8).min(data.len());
                let bytes = value.to_le_bytes();
                data[at..end].copy_from_slice(&bytes[..end - at]);
            }
            3 => {
                let end = (at + 1 + rng.below(64)).min(data.len());
                data[at..end].fill(0);
            }
            4 => {
                let end = (at + 1 + rng.below(256)).min(data.len());
                let copy = data[at..end].to_vec();
                let to = rng.below(data.len());
                data.splice(to..to, copy);
            }
            _ => data.truncate(at),
        }
    }
}

/// Decodes `data` as `kind`; the result does not matter, only that it returns.
fn decode(kind: MessageKind, encoding: Encoding, data: &[u8]) -> bool {
    match kind {
        k if k.is_points() => decode_cloud(k, encoding, data).is_ok(),
        MessageKind::Imu => decode_imu_message(encoding, data).is_ok(),
        k => decode_poses(k, encoding, data).is_ok(),
    }
}

/// Reads `path` to the end and decodes every message (and a mutated copy of each).
/// Returns the messages read.
fn read_all(rng: &mut Rng, path: &Path) -> usize {
    let Ok(container) = container_of(path) else {
        return 0;
    };
    let mut messages = 0;
    for msg in MessageSource::new(vec![(path.to_path_buf(), container)]) {
        let Ok(msg) = msg else { break };
        messages += 1;
        let kind = MessageKind::from_type(&msg.channel.message_type);
        let encoding = Encoding::from_mcap(&msg.channel.encoding);
        if let (Some(kind), Some(encoding)) = (kind, encoding) {
            decode(kind, encoding, &msg.data);
            let mut bytes = msg.data;
            mutate(rng, &mut bytes);
            decode(kind, encoding, &bytes);
        }
    }
    messages
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let seconds: u64 = args
        .next()
        .ok_or("usage: fuzz_logs SECONDS SEED_LOG...")?
        .parse()?;
    let seeds: Vec<(PathBuf, Vec<u8>)> = args
        .map(|p| std::fs::read(&p).map(|b| (PathBuf::from(p), b)))
        .collect::<Result<_, _>>()?;
    if seeds.is_empty() {
        return Err("give at least one seed log".into());
    }
    let scratch = std::env::temp_dir().join(format!("decod-fuzz-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    // Panics are caught and counted; keep their messages off the terminal after the first.
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let (mut inputs, mut panics, mut messages) = (0u64, 0u64, 0u64);
    let mut slowest = (Duration::ZERO, String::new());
    let deadline = Instant::now() + Duration::from_secs(seconds);
    while Instant::now() < deadline {
        let (seed, bytes) = &seeds[rng.below(seeds.len())];
        let mut data = bytes.clone();
        mutate(&mut rng, &mut data);
        let ext = seed.extension().and_then(|e| e.to_str()).unwrap_or("mcap");
        let path = scratch.join(format!("input.{ext}"));
        std::fs::write(&path, &data)?;
        let start = Instant::now();
        match catch_unwind(AssertUnwindSafe(|| read_all(&mut rng, &path))) {
            Ok(n) => messages += n as u64,
            Err(_) => {
                panics += 1;
                let keep = scratch.join(format!("panic-{panics}.{ext}"));
                std::fs::copy(&path, &keep)?;
                eprintln!("panic on an input saved as {}", keep.display());
            }
        }
        let took = start.elapsed();
        if took > slowest.0 {
            slowest = (took, seed.display().to_string());
        }
        inputs += 1;
    }
    println!(
        "{inputs} inputs ({messages} messages read) in {seconds} s from {} seeds; {panics} \
         panics; slowest input {:.1} ms (mutated from {})",
        seeds.len(),
        slowest.0.as_secs_f64() * 1e3,
        slowest.1
    );
    if panics > 0 {
        return Err(format!("{panics} inputs panicked").into());
    }
    Ok(())
}
