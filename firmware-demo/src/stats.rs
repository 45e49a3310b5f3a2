//! Counters and latency distributions of a run, in fixed memory so that firmware can keep
//! them for a run of any length.

/// Values below this are counted exactly; above it each power of two is split into this
/// many buckets, so a reported percentile is within 1/32 (about 3 %) of the true value.
const SUB_BUCKETS: u64 = 32;
const SUB_BUCKET_BITS: u32 = SUB_BUCKETS.trailing_zeros();
/// Largest power of two tracked; longer durations (over 12 days in microseconds) share the
/// last bucket.
const MAX_EXPONENT: u32 = 40;
const BUCKETS: usize = ((MAX_EXPONENT - SUB_BUCKET_BITS + 2) as u64 * SUB_BUCKETS) as usize;

/// A log-linear histogram of durations in microseconds.
#[derive(Clone)]
pub struct Histogram {
    counts: [u32; BUCKETS],
    count: u64,
    sum: u64,
    max: u64,
}

/// The summary, not the buckets.
impl core::fmt::Debug for Histogram {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Histogram")
            .field("count", &self.count)
            .field("p50", &self.percentile(500))
            .field("max", &self.max)
            .finish()
    }
}

impl Default for Histogram {
    fn default() -> Self {
        Self::new()
    }
}

impl Histogram {
    pub const fn new() -> Histogram {
        Histogram {
            counts: [0; BUCKETS],
            count: 0,
            sum: 0,
            max: 0,
        }
    }

    fn bucket(value: u64) -> usize {
        if value < SUB_BUCKETS {
            return value as usize;
        }
        let exponent = (63 - value.leading_zeros()).min(MAX_EXPONENT);
        let value = value.min((1 << (MAX_EXPONENT + 1)) - 1);
        let shift = exponent - SUB_BUCKET_BITS;
        let sub = (value >> shift) - SUB_BUCKETS;
        ((shift as u64 + 1) * SUB_BUCKETS + sub) as usize
    }

    /// The largest value that falls into `bucket`.
    fn bucket_upper(bucket: usize) -> u64 {
        let bucket = bucket as u64;
        if bucket < SUB_BUCKETS {
            return bucket;
        }
        let shift = bucket / SUB_BUCKETS - 1;
        let sub = bucket % SUB_BUCKETS;
        ((SUB_BUCKETS + sub + 1) << shift) - 1
    }

    pub fn record(&mut self, value_us: u64) {
        self.counts[Self::bucket(value_us)] += 1;
        self.count += 1;
        self.sum = self.sum.saturating_add(value_us);
        self.max = self.max.max(value_us);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max(&self) -> u64 {
        self.max
    }

    pub fn mean(&self) -> Option<u64> {
        self.sum.checked_div(self.count)
    }

    /// Nearest-rank percentile (`per_mille` = 500 for the median), rounded up to its bucket's
    /// upper bound and never above the maximum; `None` before any value.
    pub fn percentile(&self, per_mille: u64) -> Option<u64> {
        if self.count == 0 {
            return None;
        }
        let rank = (self.count * per_mille).div_ceil(1000).max(1);
        let mut seen = 0;
        for (bucket, &count) in self.counts.iter().enumerate() {
            seen += u64::from(count);
            if seen >= rank {
                return Some(Self::bucket_upper(bucket).min(self.max));
            }
        }
        Some(self.max)
    }
}

/// Actions of a new chunk after its first that the seam measure looks at.
pub const SEAM_WINDOW: usize = 4;

/// The seams between chunks, in action units (Euclidean norm over the action's values):
/// at each hand-over, the jump from the action run last before the new chunk takes over to
/// the chunk's first, and the largest step-to-step change among its first
/// [`SEAM_WINDOW`] + 1 actions.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Seams {
    pub count: u64,
    pub jump_sum: f64,
    pub jump_max: f64,
    pub early_step_sum: f64,
    pub early_step_max: f64,
}

impl Seams {
    /// One hand-over: `before` the last old action, `new` the chunk's actions from its take-over.
    pub fn record(&mut self, before: &[f32], new: &[f32], action_dim: usize) {
        let distance = |a: &[f32], b: &[f32]| {
            libm::sqrt(
                a.iter()
                    .zip(b)
                    .map(|(x, y)| f64::from(x - y) * f64::from(x - y))
                    .sum::<f64>(),
            )
        };
        let mut rows = new.chunks_exact(action_dim).take(SEAM_WINDOW + 1);
        let Some(first) = rows.next() else { return };
        let jump = distance(before, first);
        let mut early = 0.0f64;
        let mut previous = first;
        for row in rows {
            early = early.max(distance(previous, row));
            previous = row;
        }
        self.count += 1;
        self.jump_sum += jump;
        self.jump_max = self.jump_max.max(jump);
        self.early_step_sum += early;
        self.early_step_max = self.early_step_max.max(early);
    }

    pub fn jump_mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.jump_sum / self.count as f64)
    }

    pub fn early_step_mean(&self) -> Option<f64> {
        (self.count > 0).then(|| self.early_step_sum / self.count as f64)
    }
}

/// Everything the loop counts.
#[derive(Clone, Debug, Default)]
pub struct LoopStats {
    /// Chunks delivered.
    pub inferences: u64,
    /// Inference ticks that found an inference already waiting for the processor.
    pub skipped_inferences: u64,
    pub frames_captured: u64,
    pub frames_encoded: u64,
    /// Frames the policy would have used but that were overwritten while the processor was
    /// busy.
    pub frames_dropped: u64,
    pub control_ticks: u64,
    pub actions_executed: u64,
    /// Control ticks before the first chunk arrived (the robot waits for the policy).
    pub startup_ticks: u64,
    /// Later control ticks with no action stamped for them: the robot held still.
    pub ticks_held: u64,
    /// Actions dropped because their time had passed when their chunk arrived (or, never in
    /// a well-formed schedule, when their tick went by).
    pub stale_actions: u64,
    /// Queued actions superseded by a newer chunk at hand-over.
    pub replaced_actions: u64,
    /// Chunks that arrived after a control tick had to hold for want of them (start-up
    /// ticks excepted).
    pub deadline_misses: u64,
    /// Observation time to chunk arrival (encoding of the newest frame, waiting for the
    /// processor, inference).
    pub latency: Histogram,
    pub last_latency_us: Option<u64>,
    /// Compute time of one `push_observation`.
    pub encode_time: Histogram,
    /// Compute time of one `infer`.
    pub infer_time: Histogram,
    /// Rows of committed prefix given to the inferences, in all.
    pub prefix_rows: u64,
    pub seams: Seams,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_values_are_exact() {
        let mut histogram = Histogram::new();
        for value in [3, 1, 2] {
            histogram.record(value);
        }
        assert_eq!(histogram.percentile(500), Some(2));
        assert_eq!(histogram.percentile(1000), Some(3));
        assert_eq!(histogram.percentile(1), Some(1));
        assert_eq!(histogram.mean(), Some(2));
    }

    #[test]
    fn large_values_are_within_a_bucket() {
        let mut histogram = Histogram::new();
        for value in 1..=1000u64 {
            histogram.record(value * 1000);
        }
        let median = histogram.percentile(500).unwrap();
        assert!(
            (500_000..=500_000 + 500_000 / 32).contains(&median),
            "{median}"
        );
        let p99 = histogram.percentile(990).unwrap();
        assert!((990_000..=990_000 + 990_000 / 32).contains(&p99), "{p99}");
        assert_eq!(histogram.percentile(1000), Some(1_000_000));
        assert_eq!(histogram.max(), 1_000_000);
    }

    #[test]
    fn buckets_cover_every_value_in_order() {
        let mut previous_upper = None;
        for bucket in 0..BUCKETS {
            let upper = Histogram::bucket_upper(bucket);
            assert_eq!(Histogram::bucket(upper), bucket, "bucket {bucket}");
            if let Some(previous) = previous_upper {
                assert_eq!(Histogram::bucket(previous + 1), bucket);
            }
            previous_upper = Some(upper);
        }
        assert_eq!(Histogram::bucket(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn seams_measure_the_jump_and_the_early_steps() {
        let mut seams = Seams::default();
        // 2-D actions: the last old one at the origin; the new chunk starts 3-4-5 away,
        // then steps of 1, 2 (the largest), 0.5, 1, and 10 past the window.
        let new = [3.0, 4.0, 4.0, 4.0, 6.0, 4.0, 6.5, 4.0, 6.5, 5.0, 16.5, 5.0];
        seams.record(&[0.0, 0.0], &new, 2);
        seams.record(&[3.0, 4.0], &new[..2], 2);
        assert_eq!(seams.count, 2);
        assert_eq!(seams.jump_max, 5.0);
        assert_eq!(seams.jump_mean(), Some(2.5));
        assert_eq!(seams.early_step_max, 2.0);
        assert_eq!(seams.early_step_mean(), Some(1.0));
        assert_eq!(Seams::default().jump_mean(), None);
    }

    #[test]
    fn empty_histogram_has_no_percentile() {
        assert_eq!(Histogram::new().percentile(500), None);
        assert_eq!(Histogram::new().mean(), None);
    }
}
