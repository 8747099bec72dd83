//! Reading the golden vectors `build.rs` wrote: `dim` u32, `steps` u32, then per step `dim`
//! f32 observations and 4 f64 expected means, all little-endian (no alignment needed).

/// One row's golden sequence, borrowing the embedded bytes.
#[derive(Clone, Copy, Debug)]
pub struct Golden<'a> {
    dim: usize,
    steps: usize,
    bytes: &'a [u8],
}

/// One golden step: the observation and the float64 reference's Gaussian mean.
#[derive(Clone, Copy, Debug)]
pub struct GoldenStep {
    /// Observation values; the first `dim` are used.
    pub obs: [f32; 30],
    /// Number of observation values.
    pub dim: usize,
    /// Expected mean (float64 reference).
    pub mean: [f64; 4],
}

impl GoldenStep {
    /// The used observation values.
    pub fn obs(&self) -> &[f32] {
        self.obs.get(..self.dim).unwrap_or(&self.obs)
    }
}

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
}

impl<'a> Golden<'a> {
    /// Checks the sizes; `None` when the bytes do not hold a whole sequence.
    pub fn parse(bytes: &'a [u8]) -> Option<Self> {
        let dim = usize::try_from(u32_at(bytes, 0)?).ok()?;
        let steps = usize::try_from(u32_at(bytes, 4)?).ok()?;
        if dim > 30 || bytes.len() != 8 + steps * Self::step_len(dim) {
            return None;
        }
        Some(Self { dim, steps, bytes })
    }

    fn step_len(dim: usize) -> usize {
        dim * 4 + 4 * 8
    }

    /// Observation size.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of steps.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Step `i`.
    pub fn step(&self, i: usize) -> Option<GoldenStep> {
        let base = 8 + i * Self::step_len(self.dim);
        let b = self.bytes.get(base..base + Self::step_len(self.dim))?;
        let mut obs = [0.0f32; 30];
        for (k, o) in obs.iter_mut().take(self.dim).enumerate() {
            *o = f32::from_le_bytes(b.get(4 * k..4 * k + 4)?.try_into().ok()?);
        }
        let mut mean = [0.0f64; 4];
        for (k, m) in mean.iter_mut().enumerate() {
            let at = self.dim * 4 + 8 * k;
            *m = f64::from_le_bytes(b.get(at..at + 8)?.try_into().ok()?);
        }
        Some(GoldenStep {
            obs,
            dim: self.dim,
            mean,
        })
    }
}
