//! The fuzzers' checks (`tests/fuzz/exercise.rs`) on a few thousand mutations of each seed file,
//! with a fixed seed and on stable Rust, so that every CI run repeats them: a panic fails the
//! test. The coverage-guided fuzzers in `tests/fuzz/` go much further (see its README).

#[path = "fuzz/exercise.rs"]
mod exercise;

mod common;

use common::Rng;
use std::path::PathBuf;

/// A number below `n` (at least 1) from the shared seeded generator.
fn below(rng: &mut Rng, n: usize) -> usize {
    ((rng.next() * 0.5 + 0.5) * n.max(1) as f32) as usize % n.max(1)
}

/// One to four edits of `seed`: a flipped bit, a byte set to an edge value, a digit of the JSON
/// header changed (shapes, offsets, config values), four bytes set to a special float, or the
/// file cut short. Most edits land in the header, where the parsing is.
fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut bytes = seed.to_vec();
    let header = (8 + u64::from_le_bytes(seed[..8].try_into().unwrap()) as usize).min(seed.len());
    for _ in 0..1 + below(rng, 4) {
        let header = header.min(bytes.len());
        let at = if below(rng, 4) > 0 {
            below(rng, header)
        } else {
            below(rng, bytes.len())
        };
        match below(rng, 5) {
            0 => bytes[at] ^= 1 << below(rng, 8),
            1 => bytes[at] = [0, 1, 0x7f, 0x80, 0xff][below(rng, 5)],
            2 => {
                if let Some(d) = bytes[at..header.max(at)].iter().position(u8::is_ascii_digit) {
                    bytes[at + d] = b"0123456789"[below(rng, 10)];
                }
            }
            3 => {
                let v = [f32::NAN, f32::INFINITY, -f32::MAX, 1e30, -1.0][below(rng, 5)];
                let at = at.min(bytes.len().saturating_sub(4));
                bytes[at..at + 4].copy_from_slice(&v.to_le_bytes());
            }
            _ => bytes.truncate(at),
        }
        if bytes.len() < 9 {
            break;
        }
    }
    bytes
}

fn corpus(kind: &str) -> Vec<Vec<u8>> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fuzz/corpus")
        .join(kind);
    let mut files: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    files.into_iter().map(|p| std::fs::read(p).unwrap()).collect()
}

/// Runs `check` on every seed (each must load) and on `per_seed` mutations of each plain seed;
/// returns the fraction of mutations that loaded.
fn smoke(kind: &str, per_seed: usize, check: fn(&[u8]) -> bool) -> f64 {
    let mut rng = Rng::new(0x5EED);
    let (mut tried, mut loaded) = (0, 0);
    for seed in corpus(kind) {
        assert!(check(&seed), "a {kind} seed does not load");
        // Gzipped seeds are there for the coverage-guided fuzzer: mutated, they only fail the CRC.
        if seed.starts_with(&[0x1f, 0x8b]) {
            continue;
        }
        for _ in 0..per_seed {
            tried += 1;
            loaded += check(&mutate(&seed, &mut rng)) as usize;
        }
    }
    let fraction = loaded as f64 / tried as f64;
    println!("{kind}: {loaded} of {tried} mutations loaded");
    fraction
}

#[test]
fn mutated_weight_files_never_panic() {
    // Enough mutations reach the networks for the forward passes to be exercised too.
    assert!(smoke("weights", 20000, exercise::weights) > 0.03);
}

#[test]
fn mutated_episodes_files_never_panic() {
    assert!(smoke("episodes", 20000, exercise::episodes) > 0.03);
}

#[test]
fn mutated_driver_files_never_panic() {
    // Each mutation loads the small world again (and its fingerprint): fewer of them.
    assert!(smoke("drivers", 500, exercise::driver) > 0.03);
}

#[test]
fn mutated_sampler_files_never_panic() {
    assert!(smoke("samplers", 500, exercise::sampler) > 0.03);
}
