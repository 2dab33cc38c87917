//! Sensor messages as DDS carries them: the node reads `PointCloud2` and `Imu` samples
//! as CDR bytes and decodes them with `kfmap_bag`'s decoders, the ones `kfmap localize
//! --bag` reads recorded clouds with, and writes its map cloud with the encoder beside
//! them. One set of message types and one decoder serve bags and the node; ros2-client's
//! serde path (a second CDR decoder and a copy of every field) is left to the node's
//! small messages (docs/DESIGN.md#one-message-layer).
//!
//! ros2-client 0.12 has no subscription that hands over a sample's bytes, so these
//! readers and writers are RustDDS's own, created on the node's domain participant.

use std::convert::Infallible;

use futures::StreamExt;
use ros2_client::QosProfile;
use ros2_client::dds::rustdds::bytes::Bytes;
use ros2_client::dds::rustdds::no_key::{
    Decode, DefaultDecoder, DeserializerAdapter, SerializerAdapter, SimpleDataReader,
};
use ros2_client::dds::rustdds::{
    DomainParticipant, QosPolicies, RepresentationIdentifier, Topic, TopicDescription, no_key,
};

/// One sample's bytes: plain CDR, its 4-byte encapsulation header first, as
/// `kfmap_bag::msg`'s decoders read a bag's ROS 2 messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CdrSample(pub Vec<u8>);

/// RustDDS's adapter for [`CdrSample`]: bytes in, bytes out, no decoding.
pub struct RawCdr;

impl DeserializerAdapter<CdrSample> for RawCdr {
    type Error = Infallible;
    type Decoded = CdrSample;

    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        // The decoders name any other representation when they refuse it.
        &[
            RepresentationIdentifier::CDR_LE,
            RepresentationIdentifier::CDR_BE,
        ]
    }

    fn transform_decoded(decoded: CdrSample) -> CdrSample {
        decoded
    }
}

impl DefaultDecoder<CdrSample> for RawCdr {
    type Decoder = RawDecoder;
    const DECODER: RawDecoder = RawDecoder;
}

/// Puts the encapsulation header RustDDS took off back in front of the body.
#[derive(Clone)]
pub struct RawDecoder;

impl Decode<'_, CdrSample> for RawDecoder {
    type Error = Infallible;

    fn decode_bytes(
        self,
        body: &[u8],
        encoding: RepresentationIdentifier,
    ) -> Result<CdrSample, Infallible> {
        let mut bytes = Vec::with_capacity(body.len() + 4);
        bytes.extend_from_slice(&encoding.to_bytes());
        bytes.extend_from_slice(&[0, 0]);
        bytes.extend_from_slice(body);
        Ok(CdrSample(bytes))
    }
}

impl SerializerAdapter<CdrSample> for RawCdr {
    type Error = Infallible;

    fn output_encoding() -> RepresentationIdentifier {
        RepresentationIdentifier::CDR_LE
    }

    /// The body: RustDDS writes the encapsulation header itself. A sample of fewer than
    /// 4 bytes (none is written) sends an empty body.
    fn to_bytes(value: &CdrSample) -> Result<Bytes, Infallible> {
        Ok(Bytes::copy_from_slice(value.0.get(4..).unwrap_or_default()))
    }
}

/// A reader of `topic`'s samples as bytes.
pub fn reader(
    participant: &DomainParticipant,
    topic: &Topic,
    qos: &QosProfile,
) -> anyhow::Result<SimpleDataReader<CdrSample, RawCdr>> {
    let qos = QosPolicies::from(qos);
    let subscriber = participant
        .create_subscriber(&qos)
        .map_err(|e| anyhow::anyhow!("DDS subscriber: {e:?}"))?;
    subscriber
        .create_simple_datareader_no_key::<CdrSample, RawCdr>(topic, Some(qos))
        .map_err(|e| anyhow::anyhow!("DDS reader of {}: {e:?}", topic.name()))
}

/// A writer of `topic`'s samples from bytes.
pub fn writer(
    participant: &DomainParticipant,
    topic: &Topic,
    qos: &QosProfile,
) -> anyhow::Result<no_key::DataWriter<CdrSample, RawCdr>> {
    let qos = QosPolicies::from(qos);
    let publisher = participant
        .create_publisher(&qos)
        .map_err(|e| anyhow::anyhow!("DDS publisher: {e:?}"))?;
    publisher
        .create_datawriter_no_key::<CdrSample, RawCdr>(topic, Some(qos))
        .map_err(|e| anyhow::anyhow!("DDS writer of {}: {e:?}", topic.name()))
}

/// Hands every sample `reader` takes to `take`, with no end (the node's executor runs it
/// until the node stops).
pub async fn forward(reader: SimpleDataReader<CdrSample, RawCdr>, mut take: impl FnMut(CdrSample)) {
    let stream = reader.as_async_stream();
    futures::pin_mut!(stream);
    while let Some(item) = stream.next().await {
        match item {
            Ok(change) => take(change.into_value()),
            Err(e) => tracing::warn!("a DDS sample could not be read: {e:?}"),
        }
    }
}
