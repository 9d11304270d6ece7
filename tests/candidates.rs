//! `Simulator::rollout_candidates`: a batch of candidate action sequences gives each candidate
//! the bits of its own step-by-step rollout, from one shared state or one each, from a given
//! code or from the state's own prediction; bad arguments are typed errors.

mod common;

use common::values;
use drivesim::{Config, Error, Model, Simulator, WeightDtype};

const CONFIG: Config = common::SMALL;
/// Fewer than 8 per thread (the threads share each product's rows) and more (each thread steps
/// its own candidates).
const CANDIDATES: [usize; 2] = [5, 17];
const STEPS: usize = 4;

/// Candidate `n`'s codes and frames, one step at a time on a single simulator.
fn alone(
    model: &Model,
    h: &[f32],
    z: Option<&[f32]>,
    actions: &[f32],
    (n, of): (usize, usize),
) -> (Vec<f32>, Vec<f32>) {
    let c = CONFIG;
    let mut sim = Simulator::new(model).unwrap();
    let mut h = h.to_vec();
    let (mut codes, mut frames) = (Vec::new(), Vec::new());
    let mut out = vec![0.0; c.z_dim];
    let mut frame = vec![0.0; c.frame_len()];
    for t in 0..STEPS {
        let action = &actions[(t * of + n) * c.action_dim..][..c.action_dim];
        match (t, z) {
            (0, Some(z)) => sim.transition(z, &mut h, action, &mut out).unwrap(),
            _ => sim.transition_fed_back(&mut h, action, &mut out).unwrap(),
        }
        sim.generate(&out, &mut frame).unwrap();
        codes.extend_from_slice(&out);
        frames.extend_from_slice(&frame);
    }
    (codes, frames)
}

#[test]
fn each_candidate_gets_the_bits_of_its_own_rollout() {
    let c = CONFIG;
    for dtype in [WeightDtype::F32, WeightDtype::F16] {
        let model = Model::random(&c, 4, dtype).unwrap();
        let mut sim = Simulator::with_batch(&model, 24).unwrap().with_threads(2).unwrap();
        for candidates in CANDIDATES {
            let actions = values(3, STEPS * candidates * c.action_dim, 1.0);
            let shared_h = values(5, c.hidden_dim, 0.5);
            let own_h = values(6, candidates * c.hidden_dim, 0.5);
            let z = values(7, c.z_dim, 1.0);
            for (h, z) in [(&shared_h, Some(&z[..])), (&own_h, None), (&shared_h, None)] {
                let mut codes = vec![0.0; STEPS * candidates * c.z_dim];
                let mut frames = vec![0.0; STEPS * candidates * c.frame_len()];
                sim.rollout_candidates(h, z, candidates, &actions, &mut codes, Some(&mut frames))
                    .unwrap();
                for n in 0..candidates {
                    let state = if h.len() == c.hidden_dim {
                        &h[..]
                    } else {
                        &h[n * c.hidden_dim..][..c.hidden_dim]
                    };
                    let (want_codes, want_frames) = alone(&model, state, z, &actions, (n, candidates));
                    for t in 0..STEPS {
                        let at = |len: usize| (t * candidates + n) * len;
                        assert_eq!(
                            codes[at(c.z_dim)..][..c.z_dim],
                            want_codes[t * c.z_dim..][..c.z_dim],
                            "{dtype:?} candidate {n} of {candidates} step {t} code (z given: {})",
                            z.is_some()
                        );
                        assert_eq!(
                            frames[at(c.frame_len())..][..c.frame_len()],
                            want_frames[t * c.frame_len()..][..c.frame_len()]
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn bad_arguments_are_typed_errors() {
    let c = CONFIG;
    let model = Model::random(&c, 4, WeightDtype::F32).unwrap();
    let mut sim = Simulator::with_batch(&model, 4).unwrap();
    let h = vec![0.0; c.hidden_dim];
    let actions = vec![0.0; 2 * 4 * c.action_dim];
    let mut codes = vec![0.0; 2 * 4 * c.z_dim];
    assert!(matches!(
        sim.rollout_candidates(&h, None, 5, &actions, &mut codes, None),
        Err(Error::BatchTooLarge { max: 4, found: 5 })
    ));
    assert!(matches!(
        sim.rollout_candidates(&h, None, 0, &actions, &mut codes, None),
        Err(Error::BatchTooLarge { .. })
    ));
    assert!(matches!(
        sim.rollout_candidates(&h[1..], None, 4, &actions, &mut codes, None),
        Err(Error::BufferLength { buffer: "h", .. })
    ));
    assert!(matches!(
        sim.rollout_candidates(&h, Some(&h), 4, &actions, &mut codes, None),
        Err(Error::BufferLength { buffer: "z", .. })
    ));
    assert!(matches!(
        sim.rollout_candidates(&h, None, 4, &actions[1..], &mut codes, None),
        Err(Error::NotWholeItems { buffer: "actions", .. })
    ));
    assert!(matches!(
        sim.rollout_candidates(&h, None, 4, &actions, &mut codes[1..], None),
        Err(Error::BufferLength { buffer: "codes", .. })
    ));
    let mut nan = actions.clone();
    nan[3] = f32::NAN;
    assert!(matches!(
        sim.rollout_candidates(&h, None, 4, &nan, &mut codes, None),
        Err(Error::NonFinite {
            buffer: "actions",
            index: 3,
            ..
        })
    ));
    let mut frames = vec![0.0; 3];
    assert!(matches!(
        sim.rollout_candidates(&h, None, 4, &actions, &mut codes, Some(&mut frames)),
        Err(Error::BufferLength { buffer: "frames", .. })
    ));
}
