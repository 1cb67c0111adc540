//! The wire format of task outputs and parameters: CBOR (exact for every float) compressed
//! with zstd.

use crate::{Result, TaskError};
use serde::de::DeserializeOwned;
use serde::Serialize;

/// Encodes `v` as zstd-compressed CBOR.
pub fn encode<T: Serialize + ?Sized>(v: &T) -> Result<Vec<u8>> {
    let mut raw = Vec::new();
    ciborium::into_writer(v, &mut raw).map_err(|e| TaskError::Codec(e.to_string()))?;
    zstd::bulk::compress(&raw, 1).map_err(|e| TaskError::Codec(e.to_string()))
}

/// Decodes a stage's parameters (what [`crate::Stage::params`] gave) when a worker rebuilds it.
pub fn params<T: DeserializeOwned>(v: &serde_json::Value) -> Result<T> {
    T::deserialize(v).map_err(|e| TaskError::Codec(format!("stage parameters: {e}")))
}

/// Decodes what [`encode`] wrote.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T> {
    let raw = zstd::stream::decode_all(bytes).map_err(|e| TaskError::Codec(e.to_string()))?;
    ciborium::from_reader(raw.as_slice()).map_err(|e| TaskError::Codec(e.to_string()))
}

#[cfg(test)]
mod tests {
    #[test]
    fn floats_round_trip_exactly() {
        let v: Vec<f64> = vec![0.1, -3.5e-300, f64::MAX, 1.0 / 3.0, f64::MIN_POSITIVE];
        let f: Vec<f32> = vec![0.1, f32::INFINITY, -0.0, 1e-40];
        let back: (Vec<f64>, Vec<f32>) =
            super::decode(&super::encode(&(v.clone(), f.clone())).unwrap()).unwrap();
        assert_eq!(
            back.0.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            v.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        );
        assert_eq!(
            back.1.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            f.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        );
        assert!(super::decode::<Vec<f64>>(b"not zstd").is_err());
    }
}
