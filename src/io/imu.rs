//! sensor_msgs/Imu: the linear acceleration (specific force, m/s^2, IMU frame = body frame)
//! that the extraction uses for gravity (paper §III, basis `e1`; DESIGN.md "basis").

use super::wire::{WireReader, WireResult};

/// One IMU sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuSample {
    /// Header stamp, seconds.
    pub stamp: f64,
    /// `linear_acceleration` (specific force; points up when static), m/s^2.
    pub specific_force: [f64; 3],
}

/// Decodes sensor_msgs/Imu (orientation, angular velocity and covariances are skipped).
pub fn decode_imu<'a, R: WireReader<'a>>(r: &mut R) -> WireResult<ImuSample> {
    let header = r.header()?;
    r.quat()?;
    r.skip_f64s(9)?;
    r.vec3()?;
    r.skip_f64s(9)?;
    let specific_force = r.vec3()?;
    Ok(ImuSample {
        stamp: header.stamp,
        specific_force,
    })
}

/// IMU samples sorted by stamp.
#[derive(Clone, Debug, Default)]
pub struct ImuSeries {
    samples: Vec<ImuSample>,
}

impl ImuSeries {
    /// Sorts the samples by stamp and drops non-finite ones.
    pub fn new(mut samples: Vec<ImuSample>) -> Self {
        samples.retain(|s| s.stamp.is_finite() && s.specific_force.iter().all(|v| v.is_finite()));
        samples.sort_by(|a, b| a.stamp.total_cmp(&b.stamp));
        Self { samples }
    }

    /// The samples, sorted by stamp.
    pub fn samples(&self) -> &[ImuSample] {
        &self.samples
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether the series is empty.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Mean specific force of the samples with stamps in `[t0, t1]`; when there are none
    /// (a scan shorter than the IMU period), the sample nearest to `t1`. `None` when empty.
    pub fn mean_over(&self, t0: f64, t1: f64) -> Option<[f64; 3]> {
        let lo = self.samples.partition_point(|s| s.stamp < t0);
        let hi = self.samples.partition_point(|s| s.stamp <= t1);
        if hi > lo {
            let n = (hi - lo) as f64;
            let mut sum = [0.0; 3];
            for s in &self.samples[lo..hi] {
                for (acc, v) in sum.iter_mut().zip(s.specific_force) {
                    *acc += v;
                }
            }
            return Some(sum.map(|v| v / n));
        }
        let after = self.samples.get(hi);
        let before = hi.checked_sub(1).and_then(|i| self.samples.get(i));
        match (before, after) {
            (Some(b), Some(a)) if (a.stamp - t1).abs() < (t1 - b.stamp).abs() => {
                Some(a.specific_force)
            }
            (Some(b), _) => Some(b.specific_force),
            (None, Some(a)) => Some(a.specific_force),
            (None, None) => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_in_window_else_nearest() {
        let s = |t: f64, z: f64| ImuSample {
            stamp: t,
            specific_force: [0.0, 0.0, z],
        };
        let imu = ImuSeries::new(vec![s(0.3, 9.0), s(0.1, 10.0), s(0.2, 11.0), s(1.0, 5.0)]);
        assert_eq!(imu.mean_over(0.1, 0.2), Some([0.0, 0.0, 10.5]));
        assert_eq!(imu.mean_over(0.5, 0.55), Some([0.0, 0.0, 9.0]));
        assert_eq!(imu.mean_over(0.5, 0.9), Some([0.0, 0.0, 5.0]));
        assert_eq!(ImuSeries::default().mean_over(0.0, 1.0), None);
    }
}
