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
use ros2_client::dds::rustdds::bytes::Bytes;
use ros2_client::dds::rustdds::no_key::{
    Decode, DefaultDecoder, DeserializerAdapter, SerializerAdapter, SimpleDataReader,
};
use ros2_client::dds::rustdds::{
    DomainParticipant, QosPolicies, QosPolicyBuilder, RepresentationIdentifier, Topic,
    TopicDescription, TopicKind, no_key, policy,
};
use ros2_client::qos::History;
use ros2_client::{MessageTypeName, Name, NodeName, QosProfile};

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

/// `qos` with RustDDS's per-topic sample cache bounded to its keep-last depth.
/// RustDDS keeps every topic's received samples in a cache of its own beside the
/// reader's history, up to `ResourceLimits::max_samples` (64 when unset) whatever the
/// history depth: 64 clouds of 2.7 MB were 170 MB of the node's 290 MB
/// (docs/DESIGN.md#notes-ros2-memory).
fn bounded(qos: &QosProfile) -> QosPolicies {
    let depth = match qos.history {
        History::KeepLast { depth } => depth.clamp(1, i32::MAX as usize) as i32,
        History::KeepAll => return QosPolicies::from(qos),
    };
    QosPolicies::from(qos).modify_by(
        &QosPolicyBuilder::new()
            .resource_limits(policy::ResourceLimits {
                max_samples: depth,
                max_instances: 1,
                max_samples_per_instance: depth,
            })
            .build(),
    )
}

/// The DDS topic of ROS topic `name` (`rt/...`, as ros2-client names it) whose sample
/// cache holds no more than `qos`'s keep-last depth: created here, since the cache
/// takes its bound from the topic's QoS when the topic is made, and ros2-client's
/// topics carry no resource limits.
pub fn bounded_topic(
    participant: &DomainParticipant,
    node: &NodeName,
    name: &Name,
    type_name: &MessageTypeName,
    qos: &QosProfile,
) -> anyhow::Result<Topic> {
    let dds_name = name.to_dds_name("rt", node, "");
    participant
        .create_topic(
            dds_name.clone(),
            type_name.dds_msg_type(),
            &bounded(qos),
            TopicKind::NoKey,
        )
        .map_err(|e| anyhow::anyhow!("DDS topic {dds_name}: {e:?}"))
}

/// A reader of `topic`'s samples as bytes.
pub fn reader(
    participant: &DomainParticipant,
    topic: &Topic,
    qos: &QosProfile,
) -> anyhow::Result<SimpleDataReader<CdrSample, RawCdr>> {
    let qos = bounded(qos);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The sample cache is bounded by the keep-last depth the profile asks for (the
    /// depth is the oracle), and a keep-all profile is left without a bound.
    #[test]
    fn the_topic_cache_is_bounded_by_the_keep_last_depth() {
        let profile = QosProfile::subscription_default().history(History::KeepLast { depth: 5 });
        let limits = bounded(&profile).resource_limits().unwrap();
        assert_eq!(
            (limits.max_samples, limits.max_samples_per_instance),
            (5, 5)
        );
        let all = QosProfile::subscription_default().history(History::KeepAll);
        assert_eq!(bounded(&all).resource_limits(), None);
    }
}
