//! The value head's dreamed drives (`train heads --head value --dream-steps K`): from real
//! states, the policy drives on in the dream for K decisions over sampled futures (temperature
//! 1), the reward head scoring each decision; TD(λ) then learns from them as from the real
//! drives, each cut off after K decisions (its last state's value bootstraps it).

use drivesim::{HeadKind, Model, Simulator};

/// Dreamed drives: each decision's state `[z | h]`, its predicted reward, the state it led to,
/// and where each drive ends (counted in decisions).
pub struct Dreams {
    pub inputs: Vec<f32>,
    pub rewards: Vec<f32>,
    pub next_states: Vec<f32>,
    pub ends: Vec<usize>,
}

/// Drives of `steps` decisions from every `every`-th of the real `states` (`[z | h]` rows, the
/// speedometer at each in `speeds`), in batches, the noise drawn from `seed`.
pub fn dream(
    model: &Model,
    states: &[f32],
    speeds: &[f32],
    steps: usize,
    every: usize,
    seed: u64,
) -> Result<Dreams, String> {
    let fail = |e: drivesim::Error| e.to_string();
    if model.policy_width().is_none() || model.head_width(HeadKind::Reward).is_none() {
        return Err("dreamed drives need the model's policy and reward head (train heads --head reward first)".into());
    }
    let c = model.config();
    let (zd, hd, cols) = (c.z_dim, c.hidden_dim, c.z_dim + c.hidden_dim);
    const BATCH: usize = 256;
    let mut sim = Simulator::with_batch(model, BATCH).map_err(fail)?;
    let starts: Vec<usize> = (0..speeds.len()).step_by(every.max(1)).collect();
    let mut out = Dreams {
        inputs: Vec::new(),
        rewards: Vec::new(),
        next_states: Vec::new(),
        ends: Vec::new(),
    };
    let (mut z, mut h, mut speed) = (Vec::new(), Vec::new(), Vec::new());
    let (mut act, mut next, mut scores) = (vec![0.0; 2 * BATCH], vec![0.0; zd * BATCH], vec![0.0; 2 * BATCH]);
    for (b, batch) in starts.chunks(BATCH).enumerate() {
        let n = batch.len();
        z.clear();
        h.clear();
        speed.clear();
        for &i in batch {
            z.extend_from_slice(&states[i * cols..][..zd]);
            h.extend_from_slice(&states[i * cols + zd..][..hd]);
            speed.push(speeds[i]);
        }
        sim.set_sampling(1.0, seed.wrapping_add(b as u64)).map_err(fail)?;
        // [step][item] rows of this batch, regrouped per drive below.
        let (mut rows, mut rewards) = (
            Vec::with_capacity((steps + 1) * n * cols),
            Vec::with_capacity(steps * n),
        );
        for t in 0..=steps {
            for k in 0..n {
                rows.extend_from_slice(&z[k * zd..][..zd]);
                rows.extend_from_slice(&h[k * hd..][..hd]);
            }
            if t == steps {
                break;
            }
            sim.act(&z, &h, &mut act[..2 * n]).map_err(fail)?;
            let mut applied = act[..2 * n].to_vec();
            for k in 0..n {
                applied[2 * k] = speed[k]; // the transition reads the speed driven, the policy gives the target
                speed[k] = act[2 * k];
            }
            sim.transition(&z, &mut h, &applied, &mut next[..n * zd])
                .map_err(fail)?;
            sim.sample(&h, t as u64, &mut next[..n * zd]).map_err(fail)?;
            z.copy_from_slice(&next[..n * zd]);
            sim.reward(&z, &h, &mut scores[..2 * n]).map_err(fail)?;
            rewards.extend(scores[..2 * n].iter().step_by(2));
        }
        for k in 0..n {
            for t in 0..steps {
                out.inputs.extend_from_slice(&rows[(t * n + k) * cols..][..cols]);
                out.next_states
                    .extend_from_slice(&rows[((t + 1) * n + k) * cols..][..cols]);
                out.rewards.push(rewards[t * n + k]);
            }
            out.ends.push(out.rewards.len());
        }
    }
    Ok(out)
}
