//! Means and 95% confidence intervals over episodes.

/// Two-sided 95% quantile of Student's t with `df` degrees of freedom (t₀.₉₇₅): exact to
/// three decimals for 1–30, then the Cornish–Fisher expansion around the normal quantile
/// (error below 1e-4 for df > 30).
pub fn t975(df: usize) -> f64 {
    const TABLE: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    if let Some(t) = df.checked_sub(1).and_then(|i| TABLE.get(i)) {
        return *t;
    }
    let z = 1.959_963_985_f64;
    let n = df.max(1) as f64;
    let (z3, z5, z7) = (z.powi(3), z.powi(5), z.powi(7));
    z + (z3 + z) / (4.0 * n)
        + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * n * n)
        + (3.0 * z7 + 19.0 * z5 + 17.0 * z3 - 15.0 * z) / (384.0 * n * n * n)
}

/// Mean of `values`, `None` when empty.
pub fn mean(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        None
    } else {
        Some(values.iter().sum::<f64>() / values.len() as f64)
    }
}

/// The Student-t 95% interval of the mean of `values` (episodes as independent samples),
/// clamped to `[lo, hi]`; `None` with fewer than two values.
pub fn ci95(values: &[f64], lo: f64, hi: f64) -> Option<[f64; 2]> {
    let n = values.len();
    if n < 2 {
        return None;
    }
    let m = mean(values)?;
    let var = values.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1) as f64;
    let half = t975(n - 1) * (var / n as f64).sqrt();
    Some([(m - half).clamp(lo, hi), (m + half).clamp(lo, hi)])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_quantiles() {
        assert_eq!(t975(1), 12.706);
        assert_eq!(t975(19), 2.093);
        // Tables: t(0.975, 40) = 2.0211, t(0.975, 120) = 1.9799.
        assert!((t975(40) - 2.0211).abs() < 2e-4, "{}", t975(40));
        assert!((t975(120) - 1.9799).abs() < 1e-4);
        assert!((t975(31) - 2.0395).abs() < 3e-4, "{}", t975(31));
    }

    #[test]
    fn interval_of_known_samples() {
        // Mean 2, sample sd 1, n 4: half-width 3.182 * 0.5.
        let v = [1.0, 2.0, 3.0, 2.0];
        let sd = (2.0f64 / 3.0).sqrt();
        let [a, b] = ci95(&v, f64::MIN, f64::MAX).unwrap();
        assert!((a - (2.0 - 3.182 * sd / 2.0)).abs() < 1e-12);
        assert!((b - (2.0 + 3.182 * sd / 2.0)).abs() < 1e-12);
        assert_eq!(ci95(&[1.0, 1.0, 1.0], 0.0, 1.0), Some([1.0, 1.0]));
        assert_eq!(ci95(&[0.5], 0.0, 1.0), None);
        let [lo, hi] = ci95(&[0.0, 1.0], 0.0, 1.0).unwrap();
        assert_eq!((lo, hi), (0.0, 1.0));
    }
}
