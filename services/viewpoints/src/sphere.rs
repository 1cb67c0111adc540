//! Candidate views: directions spread uniformly on the unit sphere, and their camera angles.

/// `n` unit vectors on a Fibonacci lattice (equal-area spirals), from +z to -z.
pub fn fibonacci_sphere(n: usize) -> Vec<[f32; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * i as f64;
            [(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]
        })
        .collect()
}

/// `(azimuth, elevation)` in degrees of the orbit camera whose eye lies along unit `d` from the
/// centre (the renderer's convention: `d = (sin az cos el, -cos az cos el, sin el)`).
pub fn direction_to_view(d: [f32; 3]) -> (f32, f32) {
    let el = d[2].clamp(-1.0, 1.0).asin().to_degrees();
    let az = d[0].atan2(-d[1]).to_degrees();
    (az, el)
}

/// The unit eye direction of an orbit camera at `(azimuth, elevation)` degrees.
pub fn view_to_direction(az: f32, el: f32) -> [f32; 3] {
    let (a, e) = (az.to_radians(), el.to_radians());
    [a.sin() * e.cos(), -a.cos() * e.cos(), e.sin()]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_is_unit_and_balanced() {
        let v = fibonacci_sphere(1800);
        assert_eq!(v.len(), 1800);
        let mut mean = [0.0f64; 3];
        for d in &v {
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            assert!((l - 1.0).abs() < 1e-5);
            for k in 0..3 {
                mean[k] += d[k] as f64 / 1800.0;
            }
        }
        assert!(mean.iter().all(|m| m.abs() < 1e-2), "{mean:?}");
        for d in [[0.6f32, -0.8, 0.0], [0.0, 0.6, 0.8], [-0.36, 0.48, -0.8]] {
            let (a, e) = direction_to_view(d);
            let b = view_to_direction(a, e);
            assert!((0..3).all(|k| (b[k] - d[k]).abs() < 1e-5), "{d:?} {b:?}");
        }
    }
}
