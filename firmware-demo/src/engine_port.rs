//! The engine behind the loop's [`PolicyPort`]: the demo only wires it, the engine code is
//! the same in every build.

use scdp_engine::{Error, Noise, Policy, Prefix, PrefixMode};

use crate::control::PolicyPort;

/// Where the policy looked in the last denoising step: the end effector now and the end of the
/// path the chunk implies, in pixels (NaN where behind the camera).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnchorPath {
    pub start: [f32; 2],
    pub end: [f32; 2],
}

pub struct EnginePolicy<'w, 'a> {
    policy: Policy<'w, 'a>,
    /// How the loop's committed prefix is held; `None` ignores it (the hand-over then drops
    /// the chunk's own actions for those times as stale).
    prefix_mode: Option<PrefixMode>,
    /// Whether the queued plan after the prefix pulls the chunk (with a prefix only).
    planned: bool,
    seed: u64,
    inferences: u64,
    last_path: Option<AnchorPath>,
}

impl<'w, 'a> EnginePolicy<'w, 'a> {
    /// Inference `k` draws its initial noise from seed `seed + k`: fresh noise every time, as in
    /// training, yet a run is reproducible.
    pub fn new(
        policy: Policy<'w, 'a>,
        seed: u64,
        prefix_mode: Option<PrefixMode>,
        planned: bool,
    ) -> Self {
        EnginePolicy {
            policy,
            prefix_mode,
            planned,
            seed,
            inferences: 0,
            last_path: None,
        }
    }

    pub fn policy(&self) -> &Policy<'w, 'a> {
        &self.policy
    }

    pub fn last_path(&self) -> Option<AnchorPath> {
        self.last_path
    }
}

impl PolicyPort for EnginePolicy<'_, '_> {
    type Error = Error;

    fn push_observation(&mut self, image: &[u8], state: &[f32]) -> Result<(), Error> {
        self.policy.push_observation(image, state)
    }

    fn infer(&mut self, prefix: &[f32], planned: &[f32], chunk: &mut [f32]) -> Result<(), Error> {
        let seed = self.seed.wrapping_add(self.inferences);
        self.inferences += 1;
        let points = self.policy.config().anchor_count();
        let prefix = match self.prefix_mode {
            Some(mode) if self.planned => Prefix::new(prefix, mode).with_planned(planned),
            Some(mode) => Prefix::new(prefix, mode),
            None => Prefix::NONE,
        };
        let actions = self.policy.infer_with(Noise::Seed(seed), prefix)?;
        // The loop sizes `chunk` from the same config the model was checked against.
        chunk.copy_from_slice(actions.action());
        let anchors = actions.anchors_uv();
        let last_step = &anchors[anchors.len() - 2 * points..];
        self.last_path = Some(AnchorPath {
            start: [last_step[0], last_step[1]],
            end: [last_step[2 * points - 2], last_step[2 * points - 1]],
        });
        Ok(())
    }
}
