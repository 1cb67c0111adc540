//! World geometry: the voxel-index → world affine every reader produces, and the conversions
//! from each format's way of writing it (NIfTI sform and quaternion qform, NRRD space
//! directions and origin, OME-Zarr scale and translation).
//!
//! Affines are row-major 4x4 with last row `0 0 0 1`; voxel indices are (x, y, z).

/// A diagonal affine with the given spacing and origin (OME-Zarr's scale and translation, a
/// volume without orientation).
pub fn diag_affine(spacing: [f64; 3], origin: [f64; 3]) -> [[f64; 4]; 4] {
    [
        [spacing[0], 0.0, 0.0, origin[0]],
        [0.0, spacing[1], 0.0, origin[1]],
        [0.0, 0.0, spacing[2], origin[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// The NIfTI qform affine from the quaternion `(b, c, d)` (a = sqrt(1 - b² - c² - d²)), the
/// voxel spacing, `qfac` (±1, the sign of the z axis) and the offset (NIfTI-1 method 2).
pub fn quatern_affine(
    q: [f64; 3],
    spacing: [f64; 3],
    qfac: f64,
    offset: [f64; 3],
) -> [[f64; 4]; 4] {
    let [qb, qc, qd] = q;
    let qa = (1.0 - (qb * qb + qc * qc + qd * qd)).max(0.0).sqrt();
    let r = [
        [
            qa * qa + qb * qb - qc * qc - qd * qd,
            2.0 * (qb * qc - qa * qd),
            2.0 * (qb * qd + qa * qc),
        ],
        [
            2.0 * (qb * qc + qa * qd),
            qa * qa + qc * qc - qb * qb - qd * qd,
            2.0 * (qc * qd - qa * qb),
        ],
        [
            2.0 * (qb * qd - qa * qc),
            2.0 * (qc * qd + qa * qb),
            qa * qa + qd * qd - qc * qc - qb * qb,
        ],
    ];
    let sc = [spacing[0], spacing[1], spacing[2] * qfac];
    let mut a = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            a[i][j] = r[i][j] * sc[j];
        }
        a[i][3] = offset[i];
    }
    a[3] = [0.0, 0.0, 0.0, 1.0];
    a
}

/// The affine whose columns are the world vectors of one voxel step along x, y and z (NRRD
/// `space directions`) with `origin` (NRRD `space origin`), and the spacing those vectors
/// imply (their lengths).
pub fn affine_from_directions(dirs: [[f64; 3]; 3], origin: [f64; 3]) -> ([[f64; 4]; 4], [f64; 3]) {
    let mut a = diag_affine([1.0; 3], origin);
    let mut spacing = [1.0; 3];
    for (j, d) in dirs.iter().enumerate() {
        for i in 0..3 {
            a[i][j] = d[i];
        }
        spacing[j] = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    }
    (a, spacing)
}

/// The world origin (the translation column) of an affine.
pub fn origin(affine: &[[f64; 4]; 4]) -> [f64; 3] {
    [affine[0][3], affine[1][3], affine[2][3]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_quaternion_is_the_diagonal_affine() {
        let a = quatern_affine([0.0; 3], [0.5, 2.0, 3.0], 1.0, [1.0, 2.0, 3.0]);
        assert_eq!(a, diag_affine([0.5, 2.0, 3.0], [1.0, 2.0, 3.0]));
        let flipped = quatern_affine([0.0; 3], [1.0; 3], -1.0, [0.0; 3]);
        assert_eq!(flipped[2][2], -1.0);
    }

    #[test]
    fn a_half_turn_about_z_flips_x_and_y() {
        // b = c = 0, d = 1: a = 0, a rotation by pi about z.
        let a = quatern_affine([0.0, 0.0, 1.0], [2.0, 3.0, 4.0], 1.0, [0.0; 3]);
        assert_eq!([a[0][0], a[1][1], a[2][2]], [-2.0, -3.0, 4.0]);
    }

    #[test]
    fn directions_give_columns_and_spacing() {
        let (a, s) = affine_from_directions(
            [[-3.0, 0.0, 0.0], [0.0, -4.0, 0.0], [0.0, 0.0, 5.0]],
            [10.0, 20.0, 30.0],
        );
        assert_eq!(s, [3.0, 4.0, 5.0]);
        assert_eq!(a[0][0], -3.0);
        assert_eq!(origin(&a), [10.0, 20.0, 30.0]);
    }
}
