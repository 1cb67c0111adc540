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

/// The NIfTI-1 coordinate frames of a volume read from NIfTI, kept so that a file written for
/// it (exported labels, probabilities) carries the same sform and qform codes and matrices.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NiftiFrame {
    /// `qform_code` (0 unknown, 1 scanner, 2 aligned, 3 Talairach, 4 MNI, 5 template).
    pub qform_code: i16,
    /// `sform_code` (same codes); the sform matrix is the volume's affine.
    pub sform_code: i16,
    /// The quaternion fields as an affine ([`quatern_affine`]): the qform when
    /// `qform_code > 0`; with code 0, the fields as the header had them (written back as they
    /// were, offsets included).
    pub qform: Option<[[f64; 4]; 4]>,
}

/// The NIfTI quaternion form of an affine: `(b, c, d)`, the voxel spacing, `qfac` (±1) and the
/// offset, such that [`quatern_affine`] gives the affine back when its columns are orthogonal
/// (a rotation, a reflection of z and a scaling). Columns that are not orthogonal (shear) are
/// orthogonalised first, as `nifti_mat44_to_quatern` does, so the qform is the nearest rigid
/// frame; the sform keeps the exact affine.
pub fn affine_quatern(a: &[[f64; 4]; 4]) -> ([f64; 3], [f64; 3], f64, [f64; 3]) {
    let col = |j: usize| [a[0][j], a[1][j], a[2][j]];
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let unit = |v: [f64; 3], fallback: [f64; 3]| {
        let n = norm(v);
        if n > 0.0 {
            [v[0] / n, v[1] / n, v[2] / n]
        } else {
            fallback
        }
    };
    let dot = |u: [f64; 3], v: [f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let spacing = [norm(col(0)), norm(col(1)), norm(col(2))];
    // Gram-Schmidt on x, then y, then z (exact for orthogonal columns).
    let x = unit(col(0), [1.0, 0.0, 0.0]);
    let y0 = col(1);
    let y = unit(
        [
            y0[0] - dot(x, y0) * x[0],
            y0[1] - dot(x, y0) * x[1],
            y0[2] - dot(x, y0) * x[2],
        ],
        [0.0, 1.0, 0.0],
    );
    let z0 = col(2);
    let (zx, zy) = (dot(x, z0), dot(y, z0));
    let mut z = unit(
        [
            z0[0] - zx * x[0] - zy * y[0],
            z0[1] - zx * x[1] - zy * y[1],
            z0[2] - zx * x[2] - zy * y[2],
        ],
        [0.0, 0.0, 1.0],
    );
    // A left-handed frame is a reflection of z: qfac = -1.
    let cross = [
        x[1] * y[2] - x[2] * y[1],
        x[2] * y[0] - x[0] * y[2],
        x[0] * y[1] - x[1] * y[0],
    ];
    let qfac = if dot(cross, z) < 0.0 {
        z = [-z[0], -z[1], -z[2]];
        -1.0
    } else {
        1.0
    };
    // Rotation matrix (columns x, y, z) to a unit quaternion with a >= 0.
    let r = [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]];
    let trace = r[0][0] + r[1][1] + r[2][2];
    let (qa, qb, qc, qd);
    if trace > 0.0 {
        let s = 0.5 / (trace + 1.0).sqrt();
        qa = 0.25 / s;
        qb = (r[2][1] - r[1][2]) * s;
        qc = (r[0][2] - r[2][0]) * s;
        qd = (r[1][0] - r[0][1]) * s;
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = 2.0 * (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt();
        qa = (r[2][1] - r[1][2]) / s;
        qb = 0.25 * s;
        qc = (r[0][1] + r[1][0]) / s;
        qd = (r[0][2] + r[2][0]) / s;
    } else if r[1][1] > r[2][2] {
        let s = 2.0 * (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt();
        qa = (r[0][2] - r[2][0]) / s;
        qb = (r[0][1] + r[1][0]) / s;
        qc = 0.25 * s;
        qd = (r[1][2] + r[2][1]) / s;
    } else {
        let s = 2.0 * (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt();
        qa = (r[1][0] - r[0][1]) / s;
        qb = (r[0][2] + r[2][0]) / s;
        qc = (r[1][2] + r[2][1]) / s;
        qd = 0.25 * s;
    }
    let sign = if qa < 0.0 { -1.0 } else { 1.0 };
    ([sign * qb, sign * qc, sign * qd], spacing, qfac, origin(a))
}

/// Per-axis signs that turn coordinates of an NRRD `space` into NIfTI's RAS+ world (+x toward
/// the patient's right, +y anterior, +z superior): LPS (DICOM's) flips x and y. `None` for spaces
/// without anatomical axes (`scanner-xyz`, `3D-right-handed`, ...), taken as they are.
pub fn nrrd_space_to_ras(space: &str) -> Option<[f64; 3]> {
    match space.trim().to_ascii_lowercase().as_str() {
        "right-anterior-superior" | "ras" => Some([1.0, 1.0, 1.0]),
        "left-anterior-superior" | "las" => Some([-1.0, 1.0, 1.0]),
        "left-posterior-superior" | "lps" => Some([-1.0, -1.0, 1.0]),
        _ => None,
    }
}

/// The anatomical direction each voxel axis (x, y, z) increases toward in the RAS+ world of
/// `affine`: one of `R`/`L`, `A`/`P`, `S`/`I` per axis, each world axis used once. An oblique
/// axis takes the world axis it is closest to, choosing the assignment that is closest over
/// all three (so two axes 45° apart never land on one world axis).
pub fn axis_directions(affine: &[[f64; 4]; 4]) -> [char; 3] {
    const PERMS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    // Cosines of each voxel axis (a column) with each world axis (a row).
    let cos = |world: usize, axis: usize| {
        let n = (0..3).map(|r| affine[r][axis].powi(2)).sum::<f64>().sqrt();
        if n > 0.0 && n.is_finite() {
            affine[world][axis] / n
        } else {
            (world == axis) as u8 as f64
        }
    };
    let best = PERMS
        .iter()
        .max_by(|a, b| {
            let score = |p: &[usize; 3]| (0..3).map(|ax| cos(p[ax], ax).abs()).sum::<f64>();
            score(a).total_cmp(&score(b))
        })
        .copied()
        .unwrap_or([0, 1, 2]);
    std::array::from_fn(|ax| {
        let w = best[ax];
        let positive = cos(w, ax) >= 0.0;
        match (w, positive) {
            (0, true) => 'R',
            (0, false) => 'L',
            (1, true) => 'A',
            (1, false) => 'P',
            (2, true) => 'S',
            _ => 'I',
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_directions_follow_the_affine() {
        assert_eq!(
            axis_directions(&diag_affine([1.0; 3], [0.0; 3])),
            ['R', 'A', 'S']
        );
        // DICOM's LPS grid as NIfTI's RAS+ world: x toward the left, y posterior.
        assert_eq!(
            axis_directions(&diag_affine([-0.7, -0.7, 3.0], [0.0; 3])),
            ['L', 'P', 'S']
        );
        // A sagittal acquisition: x runs posterior → anterior, y inferior → superior, z left.
        let sag = [
            [0.0, 0.0, -1.0, 0.0],
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        assert_eq!(axis_directions(&sag), ['A', 'S', 'L']);
        // 30° oblique about z stays the nearest axes; exactly 45° still gives a permutation.
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let ob = [
            [c, -s, 0.0, 0.0],
            [s, c, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        assert_eq!(axis_directions(&ob), ['R', 'A', 'S']);
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let d = axis_directions(&[
            [h, -h, 0.0, 0.0],
            [h, h, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        let mut w: Vec<char> = d
            .iter()
            .map(|c| match c {
                'L' => 'R',
                'P' => 'A',
                'I' => 'S',
                o => *o,
            })
            .collect();
        w.sort();
        assert_eq!(w, vec!['A', 'R', 'S']);
    }

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

    fn close(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4], tol: f64) -> bool {
        (0..4).all(|i| (0..4).all(|j| (a[i][j] - b[i][j]).abs() <= tol))
    }

    #[test]
    fn quaternions_round_trip_oblique_and_reflected_affines() {
        // Rotations about each axis and an oblique one, with anisotropic spacing, an offset,
        // and both handednesses.
        let angles = [
            (0.3, 0.0, 0.0),
            (0.0, 2.5, 0.0),
            (0.0, 0.0, -1.2),
            (0.4, -0.7, 2.9),
        ];
        for &(ax, ay, az) in &angles {
            for qfac in [1.0, -1.0] {
                let (sx, cx, sy, cy, sz, cz) = (
                    f64::sin(ax),
                    f64::cos(ax),
                    f64::sin(ay),
                    f64::cos(ay),
                    f64::sin(az),
                    f64::cos(az),
                );
                let rx = [[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]];
                let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
                let rz = [[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]];
                let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| {
                    let mut m = [[0.0; 3]; 3];
                    for i in 0..3 {
                        for j in 0..3 {
                            m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
                        }
                    }
                    m
                };
                let r = mul(rz, mul(ry, rx));
                let sp = [0.7, 1.3, 3.0];
                let mut a = [[0.0; 4]; 4];
                for i in 0..3 {
                    for j in 0..3 {
                        a[i][j] = r[i][j] * sp[j] * if j == 2 { qfac } else { 1.0 };
                    }
                }
                a[0][3] = -178.0;
                a[1][3] = 11.3;
                a[2][3] = 94.3;
                a[3][3] = 1.0;
                let (q, s, f, o) = affine_quatern(&a);
                assert_eq!(f, qfac);
                assert!((s[0] - 0.7).abs() < 1e-12 && (s[2] - 3.0).abs() < 1e-12);
                let back = quatern_affine(q, s, f, o);
                assert!(close(&a, &back, 1e-9), "{a:?} vs {back:?}");
            }
        }
    }

    #[test]
    fn nrrd_spaces_map_to_ras() {
        assert_eq!(
            nrrd_space_to_ras("left-posterior-superior"),
            Some([-1.0, -1.0, 1.0])
        );
        assert_eq!(nrrd_space_to_ras("RAS"), Some([1.0, 1.0, 1.0]));
        assert_eq!(nrrd_space_to_ras("scanner-xyz"), None);
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
