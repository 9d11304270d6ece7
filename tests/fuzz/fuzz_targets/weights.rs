//! Weight files: loading, planning, and one pass through every network.
#![no_main]

#[path = "../exercise.rs"]
mod exercise;

libfuzzer_sys::fuzz_target!(|bytes: &[u8]| {
    exercise::weights(bytes);
});
