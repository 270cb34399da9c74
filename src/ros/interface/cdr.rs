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
