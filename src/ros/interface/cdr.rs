//! The bytes a message travels as: the CDR encapsulation header (`CDR_LE`, options 0), then the
//! message in little-endian CDR, as RustDDS writes a sample's payload. The same bytes go into
//! MCAP traces and, on Zenoh, into every sample and service payload (rmw_zenoh sends the
//! header too).

use rustdds::no_key::SerializerAdapter;
use rustdds::{CDRSerializerAdapter, SerializedPayload};
use serde::Serialize;

/// The CDR bytes of `msg` as the node publishes them: the encapsulation header (`CDR_LE`,
/// options 0), then the message; the serializer's error when `msg` cannot be written as CDR.
pub fn cdr_bytes<M: Serialize>(
    msg: &M,
) -> Result<Vec<u8>, <CDRSerializerAdapter<M> as SerializerAdapter<M>>::Error> {
    type Adapter<M> = CDRSerializerAdapter<M>;
    let body = <Adapter<M> as SerializerAdapter<M>>::to_bytes(msg)?;
    let payload = SerializedPayload::new_from_bytes(
        <Adapter<M> as SerializerAdapter<M>>::output_encoding(),
        body,
    );
    Ok(rustdds::bytes::Bytes::from(payload).to_vec())
}

/// Reads `bytes` as [`cdr_bytes`] writes them (either byte order of the encapsulation header
/// RustDDS reads); the reason as text when they are not a `M`. Never panics.
pub fn from_cdr_bytes<M: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<M, String> {
    use rustdds::no_key::DeserializerAdapter;
    let payload = SerializedPayload::from_bytes(&rustdds::bytes::Bytes::copy_from_slice(bytes))
        .map_err(|e| e.to_string())?;
    rustdds::CDRDeserializerAdapter::<M>::from_bytes(
        &payload.value,
        payload.representation_identifier,
    )
    .map_err(|e| e.to_string())
}
