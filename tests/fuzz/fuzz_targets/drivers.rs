//! Driver files: loading one into the small fixture's world, and one action of the driver.
#![no_main]

#[path = "../exercise.rs"]
mod exercise;

libfuzzer_sys::fuzz_target!(|bytes: &[u8]| {
    exercise::driver(bytes);
});
