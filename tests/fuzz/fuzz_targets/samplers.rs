//! Sampler files: loading one into the small fixture's world, and one sampled code through it.
#![no_main]

#[path = "../exercise.rs"]
mod exercise;

libfuzzer_sys::fuzz_target!(|bytes: &[u8]| {
    exercise::sampler(bytes);
});
