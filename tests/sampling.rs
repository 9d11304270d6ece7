//! Sampled futures (`Simulator::set_sampling`): temperature 0 is the mean bit for bit, a seed
//! gives the same bits at any thread count and in any batch, seeds differ, the noise is
//! standard normal scaled by the model's spread (correlated by `transition.L` where the model has
//! it), a texture net (`transition.texture.*`) samples in the spread's place, and bad settings
//! are typed errors. (The weight
//! files are the trainer's `random_weight_file`s: `--features train`.)
#![cfg(feature = "train")]

mod common;

use common::{fixture_path, relative_error, values, with_f32_tensors, with_texture, Io, SMALL};
use drivesim::{Environment, Error, Model, Simulator};

/// The small config's random model as a weight file, and the same with a spread head whose
/// log standard deviation is `S h + s` (`S` small, `s` = ln 0.5 on average).
fn models() -> (Model, Model) {
    let file = drivesim::train::random_weight_file(&SMALL, 3).unwrap();
    let sampled = spread_file(&file);
    (Model::from_bytes(&file).unwrap(), Model::from_bytes(&sampled).unwrap())
}

/// `file` with models()'s spread head.
fn spread_file(file: &[u8]) -> Vec<u8> {
    let (z, hd) = (SMALL.z_dim, SMALL.hidden_dim);
    let spread = [
        ("transition.S", vec![z, hd], values(1, z * hd, 0.05)),
        (
            "transition.s",
            vec![z],
            values(2, z, 0.1).iter().map(|v| v + 0.5f32.ln()).collect(),
        ),
    ];
    with_f32_tensors(file, &spread)
}

/// A lower-triangular noise factor (positive diagonal, rows of unit norm: a correlation's).
fn noise_factor() -> Vec<f32> {
    let z = SMALL.z_dim;
    let mut l = values(8, z * z, 1.0);
    for (i, row) in l.chunks_exact_mut(z).enumerate() {
        row[i] = row[i].abs() + 0.5;
        row[i + 1..].fill(0.0);
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        row.iter_mut().for_each(|v| *v /= norm);
    }
    l
}

/// models()'s spread head with `factor` as `transition.L`.
fn correlated(factor: Vec<f32>) -> Model {
    let file = spread_file(&drivesim::train::random_weight_file(&SMALL, 3).unwrap());
    let z = SMALL.z_dim;
    Model::from_bytes(&with_f32_tensors(&file, &[("transition.L", vec![z, z], factor)])).unwrap()
}

/// `n` candidates of `steps` steps from one state, candidate `k` steering `0.05 k - 0.5`.
fn candidates(sim: &mut Simulator<&Model>, n: usize, steps: usize) -> Vec<f32> {
    let (h, z) = (values(3, SMALL.hidden_dim, 0.5), values(4, SMALL.z_dim, 1.0));
    let actions: Vec<f32> = (0..steps * n)
        .flat_map(|i| [20.0, (i % n) as f32 * 0.05 - 0.5])
        .collect();
    let mut codes = vec![0.0; steps * n * SMALL.z_dim];
    sim.rollout_candidates(&h, Some(&z), n, &actions, &mut codes, None)
        .unwrap();
    codes
}

#[test]
fn temperature_zero_is_the_mean_bit_for_bit() {
    let (plain, sampled) = models();
    assert!(!plain.samples() && sampled.samples());
    let mean = candidates(&mut Simulator::with_batch(&plain, 6).unwrap(), 6, 4);
    let mut sim = Simulator::with_batch(&sampled, 6).unwrap();
    assert_eq!(candidates(&mut sim, 6, 4), mean, "sampling never set");
    sim.set_sampling(1.0, 9).unwrap();
    assert_ne!(candidates(&mut sim, 6, 4), mean);
    sim.set_sampling(0.0, 9).unwrap();
    assert_eq!(candidates(&mut sim, 6, 4), mean, "back to temperature 0");
}

#[test]
fn a_seed_gives_the_same_bits_at_any_thread_count_and_in_any_batch() {
    let (_, sampled) = models();
    same_bits_at_any_thread_count_and_in_any_batch(&sampled);
    same_bits_at_any_thread_count_and_in_any_batch(&correlated(noise_factor()));
}

fn same_bits_at_any_thread_count_and_in_any_batch(sampled: &Model) {
    let run = |threads: usize, batch: usize, seed: u64| {
        let mut sim = Simulator::with_batch(sampled, batch)
            .unwrap()
            .with_threads(threads)
            .unwrap();
        sim.set_sampling(1.0, seed).unwrap();
        candidates(&mut sim, batch, 5)
    };
    let step_major = |codes: Vec<f32>, n: usize, keep: usize| -> Vec<f32> {
        codes
            .chunks_exact(n * SMALL.z_dim)
            .flat_map(|step| step[..keep * SMALL.z_dim].to_vec())
            .collect()
    };
    let one = run(1, 4, 11);
    assert_eq!(run(2, 4, 11), one);
    assert_eq!(run(3, 4, 11), one);
    // Candidate k of a batch of 9 is candidate k of a batch of 4: the noise is the item's.
    assert_eq!(step_major(run(1, 9, 11), 9, 4), one);
    assert_ne!(run(1, 4, 12), one, "another seed, another future");

    // A rollout is item 0: candidate 0 from the same state is the same dream.
    let mut sim = Simulator::new(sampled).unwrap();
    sim.set_sampling(1.0, 11).unwrap();
    let seed = values(4, SMALL.z_dim, 1.0);
    let actions: Vec<f32> = (0..5).flat_map(|_| [20.0, -0.5]).collect();
    let mut codes = vec![0.0; 5 * SMALL.z_dim];
    sim.rollout_from_codes(&seed, &actions, &mut codes, None).unwrap();
    let zero_h = vec![0.0; SMALL.hidden_dim];
    let mut first = vec![0.0; 5 * SMALL.z_dim];
    sim.rollout_candidates(&zero_h, Some(&seed), 1, &actions, &mut first, None)
        .unwrap();
    assert_eq!(codes, first);
}

#[test]
fn a_texture_net_samples_in_the_spreads_place() {
    let (plain, _) = models();
    let file = drivesim::train::random_weight_file(&SMALL, 3).unwrap();
    let textured = Model::from_bytes(&with_texture(&file, 7, 11)).unwrap();
    assert!(textured.samples() && !textured.samples_correlated());
    assert_eq!((textured.texture_width(), plain.texture_width()), (Some(7), None));
    let mean = candidates(&mut Simulator::with_batch(&plain, 6).unwrap(), 6, 4);
    let mut sim = Simulator::with_batch(&textured, 6).unwrap();
    assert_eq!(candidates(&mut sim, 6, 4), mean, "sampling never set");
    sim.set_sampling(1.0, 9).unwrap();
    let drawn = candidates(&mut sim, 6, 4);
    assert_ne!(drawn, mean);
    sim.set_sampling(0.5, 9).unwrap();
    assert_ne!(
        candidates(&mut sim, 6, 4),
        drawn,
        "the temperature scales the noise it reads"
    );
    // With the spread head too, the texture net samples: the same draws.
    let both = Model::from_bytes(&with_texture(&spread_file(&file), 7, 11)).unwrap();
    let mut sim = Simulator::with_batch(&both, 6).unwrap();
    sim.set_sampling(1.0, 9).unwrap();
    assert_eq!(candidates(&mut sim, 6, 4), drawn);
    same_bits_at_any_thread_count_and_in_any_batch(&textured);
    // Wider than the hidden state, or half a net: typed errors.
    let wide = with_texture(&file, SMALL.hidden_dim + 1, 11);
    assert!(matches!(Model::from_bytes(&wide), Err(Error::Config { .. })));
    let half = with_f32_tensors(&file, &[("transition.texture.hidden.bias", vec![3], vec![0.0; 3])]);
    assert!(matches!(Model::from_bytes(&half), Err(Error::MissingTensor { .. })));
}

#[test]
fn the_texture_net_is_read_as_pytorch_writes_it() {
    // weights/drivesim_reference/fixtures.py's texture_f32: a net whose noise columns are zero, so that a sample
    // is the mean plus its offset of h alone, at any temperature and seed.
    let model = Model::load(fixture_path("texture_f32.safetensors")).unwrap();
    let io = Io::open("texture_f32.io.safetensors");
    let (h, mut codes) = (io.values("h"), io.values("mean"));
    let mut sim = Simulator::with_batch(&model, 5).unwrap();
    sim.set_sampling(0.7, 3).unwrap();
    sim.sample(&h, 4, &mut codes).unwrap();
    let error = relative_error(&codes, &io.values("sampled"));
    assert!(error < 1e-5, "relative error {error}");
}

#[test]
fn the_noise_is_standard_normal_scaled_by_the_spread() {
    let (plain, sampled) = models();
    let n = 64;
    let mean = candidates(&mut Simulator::with_batch(&plain, n).unwrap(), n, 1);
    let mut sim = Simulator::with_batch(&sampled, n).unwrap();
    sim.set_sampling(2.0, 5).unwrap();
    let drawn = candidates(&mut sim, n, 1);
    // The first step's hidden state is the same for both: the spread is exp(S h' + s).
    let mut h = vec![0.0; n * SMALL.hidden_dim];
    let mut z = vec![0.0; n * SMALL.z_dim];
    let (h0, z0) = (values(3, SMALL.hidden_dim, 0.5), values(4, SMALL.z_dim, 1.0));
    for (hn, zn) in h
        .chunks_exact_mut(SMALL.hidden_dim)
        .zip(z.chunks_exact_mut(SMALL.z_dim))
    {
        hn.copy_from_slice(&h0);
        zn.copy_from_slice(&z0);
    }
    let actions: Vec<f32> = (0..n).flat_map(|i| [20.0, i as f32 * 0.05 - 0.5]).collect();
    let mut next = vec![0.0; n * SMALL.z_dim];
    let mut plain_sim = Simulator::with_batch(&sampled, n).unwrap();
    plain_sim.transition(&z, &mut h, &actions, &mut next).unwrap();
    assert_eq!(next, mean);
    let s = values(2, SMALL.z_dim, 0.1);
    let big_s = values(1, SMALL.z_dim * SMALL.hidden_dim, 0.05);
    let mut normals = Vec::new();
    for (i, (d, m)) in drawn.iter().zip(&mean).enumerate() {
        let (item, dim) = (i / SMALL.z_dim, i % SMALL.z_dim);
        let hn = &h[item * SMALL.hidden_dim..][..SMALL.hidden_dim];
        let log_sigma: f64 = s[dim] as f64
            + 0.5f64.ln()
            + big_s[dim * SMALL.hidden_dim..][..SMALL.hidden_dim]
                .iter()
                .zip(hn)
                .map(|(a, b)| *a as f64 * *b as f64)
                .sum::<f64>();
        normals.push((d - m) as f64 / (2.0 * log_sigma.exp()));
    }
    let count = normals.len() as f64;
    let mean_noise = normals.iter().sum::<f64>() / count;
    let var = normals.iter().map(|x| (x - mean_noise).powi(2)).sum::<f64>() / count;
    assert!(
        mean_noise.abs() < 0.15 && (var - 1.0).abs() < 0.25,
        "{mean_noise} {var} over {count}"
    );
}

#[test]
fn correlated_noise_is_the_factor_times_the_independent_noise() {
    let (_, sampled) = models();
    let n = 16;
    let draw = |model: &Model, temperature: f32| {
        let mut sim = Simulator::with_batch(model, n).unwrap();
        sim.set_sampling(temperature, 5).unwrap();
        candidates(&mut sim, n, 1)
    };
    let (mean, independent) = (draw(&sampled, 0.0), draw(&sampled, 1.5));
    // The identity factor is the independent noise, bit for bit.
    let z = SMALL.z_dim;
    let identity: Vec<f32> = (0..z * z).map(|i| (i % (z + 1) == 0) as u8 as f32).collect();
    assert_eq!(draw(&correlated(identity), 1.5), independent);
    // Any other: per item, (sample - mean) / spread is L times the independent one's.
    let factor = noise_factor();
    let model = correlated(factor.clone());
    assert!(model.samples_correlated() && !sampled.samples_correlated());
    let drawn = draw(&model, 1.5);
    assert_eq!(draw(&model, 0.0), mean, "temperature 0 stays the mean");
    let spread: Vec<f64> = log_sigma_of_first_step(n).iter().map(|l| 1.5 * l.exp()).collect();
    for item in 0..n {
        let at = |codes: &[f32], d: usize| (codes[item * z + d] - mean[item * z + d]) as f64 / spread[item * z + d];
        for d in 0..z {
            let expected: f64 = (0..z).map(|j| factor[d * z + j] as f64 * at(&independent, j)).sum();
            assert!((at(&drawn, d) - expected).abs() < 1e-3, "item {item}, dimension {d}");
        }
    }
}

/// The spread head's `S h' + s` (models()'s) of the first step of `candidates(_, n, 1)`.
fn log_sigma_of_first_step(n: usize) -> Vec<f64> {
    let (plain, _) = models();
    let (hd, z) = (SMALL.hidden_dim, SMALL.z_dim);
    let (h0, z0) = (values(3, hd, 0.5), values(4, z, 1.0));
    let mut h: Vec<f32> = (0..n).flat_map(|_| h0.clone()).collect();
    let codes: Vec<f32> = (0..n).flat_map(|_| z0.clone()).collect();
    let actions: Vec<f32> = (0..n).flat_map(|i| [20.0, i as f32 * 0.05 - 0.5]).collect();
    let mut next = vec![0.0; n * z];
    Simulator::with_batch(&plain, n)
        .unwrap()
        .transition(&codes, &mut h, &actions, &mut next)
        .unwrap();
    let (s, big_s) = (values(2, z, 0.1), values(1, z * hd, 0.05));
    let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
    (0..n * z)
        .map(|i| {
            let (item, d) = (i / z, i % z);
            s[d] as f64 + 0.5f64.ln() + dot(&big_s[d * hd..][..hd], &h[item * hd..][..hd])
        })
        .collect()
}

#[test]
fn bad_settings_are_typed_errors() {
    let (plain, sampled) = models();
    let mut sim = Simulator::new(&plain).unwrap();
    assert!(matches!(sim.set_sampling(1.0, 0), Err(Error::NoSampling)));
    sim.set_sampling(0.0, 0).unwrap();
    let mut sim = Simulator::new(&sampled).unwrap();
    for bad in [-1.0, f32::NAN, f32::INFINITY] {
        assert!(matches!(sim.set_sampling(bad, 0), Err(Error::Setting { .. })));
    }
    assert_eq!(sim.sampling(), (0.0, 0), "a refused setting changes nothing");
    // A spread head of the wrong shape, or half of one, does not load.
    let file = drivesim::train::random_weight_file(&SMALL, 3).unwrap();
    let wrong = with_f32_tensors(&file, &[("transition.S", vec![3, 3], vec![0.0; 9])]);
    assert!(Model::from_bytes(&wrong).is_err());
    let half = with_f32_tensors(&file, &[("transition.s", vec![SMALL.z_dim], vec![0.0; SMALL.z_dim])]);
    assert!(Model::from_bytes(&half).is_err());
    // A noise factor without the spread head, or of the wrong shape, does not either.
    let z = SMALL.z_dim;
    let alone = with_f32_tensors(&file, &[("transition.L", vec![z, z], vec![0.0; z * z])]);
    assert!(matches!(Model::from_bytes(&alone), Err(Error::MissingTensor { name }) if name == "transition.S"));
    let square = with_f32_tensors(
        &spread_file(&file),
        &[("transition.L", vec![z, z + 1], vec![0.0; z * (z + 1)])],
    );
    assert!(matches!(Model::from_bytes(&square), Err(Error::Shape { .. })));
}

#[test]
fn an_environment_samples_its_steps_and_repeats_after_a_reset() {
    let (_, sampled) = models();
    let mut env = Environment::new(&sampled, 2, 4).unwrap();
    let seeds = values(7, 2 * SMALL.z_dim, 1.0);
    let drive = |env: &mut Environment<&Model>| {
        env.reset_from_codes(&seeds, &[]).unwrap();
        let mut codes = Vec::new();
        for _ in 0..4 {
            env.step(&[20.0, 0.3, 20.0, -0.3]).unwrap();
            codes.extend_from_slice(env.codes());
        }
        codes
    };
    let mean = drive(&mut env);
    env.set_sampling(1.0, 3).unwrap();
    let first = drive(&mut env);
    assert_ne!(first, mean);
    assert_eq!(drive(&mut env), first, "a reset and the same actions: the same drive");
}

#[test]
fn a_failed_step_leaves_the_environment_to_be_reset_not_half_stepped() {
    // A transition whose next code overflows: every step's prediction is infinite.
    let file = spread_file(&drivesim::train::random_weight_file(&SMALL, 3).unwrap());
    let (z, hd) = (SMALL.z_dim, SMALL.hidden_dim);
    let huge = [
        ("transition.A", vec![z, hd], vec![3e38; z * hd]),
        ("transition.a", vec![z], vec![3e38; z]),
    ];
    let model = Model::from_bytes(&with_f32_tensors(&file, &huge)).unwrap();
    let mut env = Environment::new(&model, 2, 4).unwrap();
    env.reset_from_codes(&values(7, 2 * z, 1.0), &[]).unwrap();
    // Bad actions are refused before anything changes: the drives stay as they were.
    let codes = env.codes().to_vec();
    assert!(matches!(env.step(&[20.0, 0.1, 20.0]), Err(Error::BufferLength { .. })));
    assert!(matches!(
        env.step(&[20.0, f32::NAN, 20.0, 0.1]),
        Err(Error::NonFinite { .. })
    ));
    assert!(env.is_seeded() && env.codes() == codes);
    // A step that fails on its way (here, a prediction that is not finite) is never half a
    // step: the drives must be reset.
    assert!(matches!(
        env.step(&[20.0, 0.1, 20.0, 0.1]),
        Err(Error::NonFiniteOutput { .. })
    ));
    assert!(!env.is_seeded());
    assert!(matches!(env.step(&[20.0, 0.1, 20.0, 0.1]), Err(Error::NotSeeded)));
    env.reset_from_codes(&values(7, 2 * z, 1.0), &[]).unwrap();
    assert!(env.is_seeded());
}
