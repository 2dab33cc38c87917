// fdpeer: a minimal Fast DDS 2.x peer for kfmap-ros2 interop tests.
//
// Publishes sensor_msgs/PointCloud2 (synthetic plane points or PCD scans) and subscribes
// to PoseWithCovarianceStamped, latched PointCloud2 and DiagnosticArray topics, with the
// ROS 2 DDS names (topic "rt/<name>", type "<pkg>::msg::dds_::<Name>_"). Every event is
// one JSON line on stdout. Fast DDS's own defaults are kept (shared-memory + UDPv4
// transports, XML profiles from FASTRTPS_DEFAULT_PROFILES_FILE or
// DEFAULT_FASTRTPS_PROFILES.xml) unless a flag says otherwise.
//
// Usage: fdpeer [options]   (see usage() below). Built by tools/fastdds/build.sh; run
// beside the node by tools/fastdds/run.sh (README there).

#include "ros2_msgsPubSubTypes.h"

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/domain/DomainParticipantListener.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/DataWriterListener.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/Topic.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

using namespace eprosima::fastdds::dds;
namespace rtps = eprosima::fastrtps::rtps;

namespace sm = sensor_msgs::msg::dds_;
namespace gm = geometry_msgs::msg::dds_;
namespace dm = diagnostic_msgs::msg::dds_;

static std::mutex out_mutex;
static const auto t0 = std::chrono::steady_clock::now();

static double now_s()
{
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

static double wall_s()
{
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

static std::string esc(const std::string& s)
{
    std::string o;
    for (char c : s)
    {
        if (c == '"' || c == '\\')
        {
            o += '\\';
            o += c;
        }
        else if (static_cast<unsigned char>(c) < 0x20)
        {
            char b[8];
            std::snprintf(b, sizeof b, "\\u%04x", c);
            o += b;
        }
        else
        {
            o += c;
        }
    }
    return o;
}

// One JSON object per line: `body` is the object's members without braces.
static void emit(const std::string& body)
{
    std::lock_guard<std::mutex> lock(out_mutex);
    std::printf("{\"t\":%.6f,%s}\n", now_s(), body.c_str());
    std::fflush(stdout);
}

static std::string ros_topic(const std::string& name)
{
    // ROS 2 topic "/a/b" is DDS topic "rt/a/b".
    return "rt" + (name.empty() || name[0] != '/' ? "/" + name : name);
}

struct Options
{
    int domain = -1;
    // Publisher of clouds.
    std::string pub_points;
    int points = 1000;
    std::string pcd_dir;
    int pcd_first = 0;  // index of the first PCD file
    int pcd_count = 0;
    std::string stamps_file;  // one stamp per cloud, seconds (instead of stamp0 + k step)
    // Publisher of IMU samples, interleaved with the clouds.
    std::string pub_imu;
    std::string imu_file;  // "t ax ay az gx gy gz" per line, t on the clouds' clock
    double imu_ahead = 0.05;  // samples up to this past a cloud's stamp go out before it
    double rate = 10.0;
    int count = 20;
    bool reliable = false;
    int depth = 5;
    bool async = false;
    double wait_match = 15.0;
    double stamp0 = -1.0;  // first cloud's stamp, seconds (negative: wall clock)
    double stamp_step = 0.0;  // stamp increment per cloud, seconds (0: 1 / rate)
    std::string initial_pose;  // "x,y,z,qx,qy,qz,qw" for /initialpose before the clouds
    std::string tf_static;  // "parent,child,x,y,z,qx,qy,qz,qw" latched on /tf_static
    std::string frame = "lidar";
    int point_step = 16;  // bytes per point: x, y, z then zero padding
    // Subscribers.
    std::string sub_pose;
    std::string sub_cloud;
    bool cloud_transient_local = true;
    std::string sub_diag;
    std::string sub_vector;
    bool best_effort_sub = false;
    // Run length after publishing (or in total with no publisher).
    double linger = 5.0;
    double duration = 0.0;
    int expect_poses = -1;  // stop once this many poses came (with nothing left to send)
    int expect_clouds = -1;
    bool until_last_pose = false;  // stop early once the last cloud's pose came
    double lockstep = 0.0;  // > 0: wait up to this long for each cloud's diagnostics
    // Transports / QoS.
    bool qos_from_xml = false;
    bool no_shm = false;
    int socket_buffer = 0;
    bool discovery_log = true;
};

static void usage()
{
    std::fprintf(stderr,
        "fdpeer [options]\n"
        "  --domain N              DDS domain (default ROS_DOMAIN_ID or 0)\n"
        "  --pub-points TOPIC      publish sensor_msgs/PointCloud2 on TOPIC (ROS name, e.g. /points)\n"
        "  --points N              synthetic cloud: N points on a plane (x,y,z float32, point_step 16)\n"
        "  --pcd-dir DIR           publish DIR/000000.pcd ... (binary PCD, x y z first) instead\n"
        "  --pcd-count K           how many PCD files to cycle through (default: until one is missing)\n"
        "  --pcd-first K           the first PCD file's index (0)\n"
        "  --stamps-file FILE      cloud k's stamp from line k of FILE (seconds; a dataset's own)\n"
        "  --pub-imu TOPIC         publish sensor_msgs/Imu from --imu-file, interleaved: before each\n"
        "                          cloud the samples up to --imu-ahead S past its stamp (0.05), as a\n"
        "                          driver's IMU runs ahead of a cloud sent when its sweep ends\n"
        "  --imu-file FILE         \"t ax ay az gx gy gz\" per line (s, m/s^2, rad/s; the clouds' clock)\n"
        "  --rate HZ               publication rate (10)\n"
        "  --count K               clouds to publish (20)\n"
        "  --reliable              reliable writer (default best effort, as ROS 2 sensor data QoS)\n"
        "  --depth D               writer keep-last depth (5)\n"
        "  --async                 asynchronous publish mode (rmw_fastrtps Humble's default)\n"
        "  --wait-match S          wait up to S s for a matched reader before publishing (15)\n"
        "  --stamp0 S              first stamp, seconds; then +1/rate each (default: wall clock)\n"
        "  --initial-pose X,Y,Z,QX,QY,QZ,QW\n"
        "                          publish it once on /initialpose (frame map, reliable)\n"
        "                          before the first cloud, as RViz's 2D Pose Estimate does\n"
        "  --tf-static PARENT,CHILD,X,Y,Z,QX,QY,QZ,QW\n"
        "                          latch one transform on /tf_static (reliable, transient\n"
        "                          local) at start-up: the sensor's mounting\n"
        "  --stamp-step S          stamp increment per cloud instead of 1/rate (a dataset's\n"
        "                          spacing, published slower or faster than recorded)\n"
        "  --frame ID              header.frame_id of the clouds (lidar)\n"
        "  --point-step S          bytes per point, >= 12 (16; 24 makes a 112k-point scan 2.7 MB)\n"
        "  --sub-pose TOPIC        subscribe geometry_msgs/PoseWithCovarianceStamped (reliable, keep-last 10)\n"
        "  --sub-cloud TOPIC       subscribe sensor_msgs/PointCloud2 (reliable, transient local, keep-last 1)\n"
        "  --volatile-cloud        ... with volatile durability instead\n"
        "  --sub-diag TOPIC        subscribe diagnostic_msgs/DiagnosticArray (reliable, keep-last 10)\n"
        "  --sub-vector TOPIC      subscribe geometry_msgs/Vector3Stamped (reliable, transient local,\n"
        "                          keep-last 1: the node's gravity)\n"
        "  --best-effort-sub       subscribers best effort instead of reliable\n"
        "  --linger S              keep running S s after the last cloud (5)\n"
        "  --duration S            total run time with no publisher (default: linger)\n"
        "  --expect-poses N        stop early after N poses (once publishing is done)\n"
        "  --expect-clouds N       stop early after N subscribed clouds (once publishing is done)\n"
        "  --until-last-pose       stop early once the pose stamped as the last cloud came\n"
        "  --lockstep S            after each cloud wait (at most S s) for the node's diagnostics\n"
        "                          stamped as it before the next (needs --sub-diag): a loaded\n"
        "                          host slows the drive instead of making the node skip clouds\n"
        "  --qos-from-xml          keep the XML profile's QoS for the endpoints (no overrides in code)\n"
        "  --no-shm                UDPv4 transport only (builtin transports off)\n"
        "  --socket-buffer BYTES   UDP send and receive buffer sizes (with --no-shm)\n"
        "  --quiet-discovery       do not print remote participants and endpoints\n");
}

static bool parse(int argc, char** argv, Options& o)
{
    for (int i = 1; i < argc; ++i)
    {
        std::string a = argv[i];
        auto val = [&](void) -> std::string {
            if (i + 1 >= argc)
            {
                std::fprintf(stderr, "%s needs a value\n", a.c_str());
                std::exit(2);
            }
            return argv[++i];
        };
        if (a == "--domain") o.domain = std::stoi(val());
        else if (a == "--pub-points") o.pub_points = val();
        else if (a == "--points") o.points = std::stoi(val());
        else if (a == "--pcd-dir") o.pcd_dir = val();
        else if (a == "--pcd-count") o.pcd_count = std::stoi(val());
        else if (a == "--pcd-first") o.pcd_first = std::stoi(val());
        else if (a == "--stamps-file") o.stamps_file = val();
        else if (a == "--pub-imu") o.pub_imu = val();
        else if (a == "--imu-file") o.imu_file = val();
        else if (a == "--imu-ahead") o.imu_ahead = std::stod(val());
        else if (a == "--rate") o.rate = std::stod(val());
        else if (a == "--count") o.count = std::stoi(val());
        else if (a == "--reliable") o.reliable = true;
        else if (a == "--depth") o.depth = std::stoi(val());
        else if (a == "--async") o.async = true;
        else if (a == "--wait-match") o.wait_match = std::stod(val());
        else if (a == "--stamp0") o.stamp0 = std::stod(val());
        else if (a == "--stamp-step") o.stamp_step = std::stod(val());
        else if (a == "--initial-pose") o.initial_pose = val();
        else if (a == "--tf-static") o.tf_static = val();
        else if (a == "--frame") o.frame = val();
        else if (a == "--point-step") o.point_step = std::max(12, std::stoi(val()));
        else if (a == "--sub-pose") o.sub_pose = val();
        else if (a == "--sub-cloud") o.sub_cloud = val();
        else if (a == "--volatile-cloud") o.cloud_transient_local = false;
        else if (a == "--sub-diag") o.sub_diag = val();
        else if (a == "--sub-vector") o.sub_vector = val();
        else if (a == "--best-effort-sub") o.best_effort_sub = true;
        else if (a == "--linger") o.linger = std::stod(val());
        else if (a == "--duration") o.duration = std::stod(val());
        else if (a == "--expect-poses") o.expect_poses = std::stoi(val());
        else if (a == "--expect-clouds") o.expect_clouds = std::stoi(val());
        else if (a == "--until-last-pose") o.until_last_pose = true;
        else if (a == "--lockstep") o.lockstep = std::stod(val());
        else if (a == "--qos-from-xml") o.qos_from_xml = true;
        else if (a == "--no-shm") o.no_shm = true;
        else if (a == "--socket-buffer") o.socket_buffer = std::stoi(val());
        else if (a == "--quiet-discovery") o.discovery_log = false;
        else if (a == "-h" || a == "--help")
        {
            usage();
            std::exit(0);
        }
        else
        {
            std::fprintf(stderr, "unknown option %s\n", a.c_str());
            usage();
            return false;
        }
    }
    return true;
}

// ---------------------------------------------------------------------------------------
// Discovery: what the remote side announces (names, types, topic kind, QoS, locators).

static std::string locators_json(const rtps::RemoteLocatorList& l)
{
    std::ostringstream s;
    s << "[";
    bool first = true;
    for (const auto& loc : l.unicast)
    {
        s << (first ? "" : ",") << "\"" << loc << "\"";
        first = false;
    }
    for (const auto& loc : l.multicast)
    {
        s << (first ? "" : ",") << "\"mc:" << loc << "\"";
        first = false;
    }
    s << "]";
    return s.str();
}

static std::string guid_str(const rtps::GUID_t& g)
{
    std::ostringstream s;
    s << g;
    return s.str();
}

struct ParticipantListener : public DomainParticipantListener
{
    bool log = true;

    void on_participant_discovery(DomainParticipant*, rtps::ParticipantDiscoveryInfo&& info) override
    {
        if (!log) return;
        const char* st[] = {"discovered", "changed_qos", "removed", "dropped", "ignored"};
        std::ostringstream vid;
        vid << int(info.info.m_VendorId[0]) << "." << int(info.info.m_VendorId[1]);
        emit("\"event\":\"participant\",\"status\":\"" + std::string(st[info.status % 5]) +
             "\",\"name\":\"" + esc(info.info.m_participantName.to_string()) +
             "\",\"vendor\":\"" + vid.str() + "\",\"guid\":\"" + guid_str(info.info.m_guid) +
             "\",\"metatraffic\":" + locators_json(info.info.metatraffic_locators) +
             ",\"default\":" + locators_json(info.info.default_locators));
    }

    void on_subscriber_discovery(DomainParticipant*, rtps::ReaderDiscoveryInfo&& info) override
    {
        if (!log) return;
        const auto& d = info.info;
        emit("\"event\":\"remote_reader\",\"status\":" + std::to_string(int(info.status)) +
             ",\"topic\":\"" + esc(d.topicName().to_string()) + "\",\"type\":\"" +
             esc(d.typeName().to_string()) + "\",\"keyed\":" +
             (d.topicKind() == rtps::WITH_KEY ? "true" : "false") + ",\"reliable\":" +
             (d.m_qos.m_reliability.kind == RELIABLE_RELIABILITY_QOS ? "true" : "false") +
             ",\"durability\":" + std::to_string(int(d.m_qos.m_durability.kind)) +
             ",\"locators\":" + locators_json(d.remote_locators()));
    }

    void on_publisher_discovery(DomainParticipant*, rtps::WriterDiscoveryInfo&& info) override
    {
        if (!log) return;
        const auto& d = info.info;
        emit("\"event\":\"remote_writer\",\"status\":" + std::to_string(int(info.status)) +
             ",\"topic\":\"" + esc(d.topicName().to_string()) + "\",\"type\":\"" +
             esc(d.typeName().to_string()) + "\",\"keyed\":" +
             (d.topicKind() == rtps::WITH_KEY ? "true" : "false") + ",\"reliable\":" +
             (d.m_qos.m_reliability.kind == RELIABLE_RELIABILITY_QOS ? "true" : "false") +
             ",\"durability\":" + std::to_string(int(d.m_qos.m_durability.kind)) +
             ",\"locators\":" + locators_json(d.remote_locators()));
    }
};

// ---------------------------------------------------------------------------------------
// Readers.

static std::atomic<int> poses_received{0};
static std::atomic<int> clouds_received{0};
static std::atomic<int> diags_received{0};
static std::atomic<int> vectors_received{0};
// The stamp of the newest pose received (for --until-last-pose).
static std::atomic<double> last_pose_stamp{-1.0};
// The stamp of the newest diagnostics received (for --lockstep).
static std::atomic<double> last_diag_stamp{-1.0};

// Stamps travel as (sec, nanosec): equal to a microsecond is the same message's.
static bool same_stamp(double a, double b)
{
    return std::abs(a - b) < 1e-6;
}

struct ReaderEvents : public DataReaderListener
{
    std::string topic;

    void on_subscription_matched(DataReader*, const SubscriptionMatchedStatus& s) override
    {
        emit("\"event\":\"reader_matched\",\"topic\":\"" + topic + "\",\"current\":" +
             std::to_string(s.current_count) + ",\"change\":" + std::to_string(s.current_count_change));
    }

    void on_requested_incompatible_qos(DataReader*, const RequestedIncompatibleQosStatus& s) override
    {
        emit("\"event\":\"reader_incompatible_qos\",\"topic\":\"" + topic + "\",\"policy\":" +
             std::to_string(s.last_policy_id) + ",\"total\":" + std::to_string(s.total_count));
    }

    void on_sample_lost(DataReader*, const SampleLostStatus& s) override
    {
        emit("\"event\":\"sample_lost\",\"topic\":\"" + topic + "\",\"total\":" +
             std::to_string(s.total_count));
    }

    void on_sample_rejected(DataReader*, const SampleRejectedStatus& s) override
    {
        emit("\"event\":\"sample_rejected\",\"topic\":\"" + topic + "\",\"total\":" +
             std::to_string(s.total_count) + ",\"reason\":" + std::to_string(int(s.last_reason)));
    }
};

static double stamp_of(const builtin_interfaces::msg::dds_::Time_& t)
{
    return t.sec() + t.nanosec() * 1e-9;
}

// A reader of messages `M`: counts each valid sample in `received` and prints it with
// `describe(topic, message, count)` (one event or more).
template <class M>
struct Reader : public ReaderEvents
{
    using Describe = void (*)(const std::string& topic, const M&, int n);

    Reader(std::atomic<int>& received, Describe describe) : received(received), describe(describe) {}

    std::atomic<int>& received;
    Describe describe;

    void on_data_available(DataReader* reader) override
    {
        M m;
        SampleInfo info;
        while (reader->take_next_sample(&m, &info) == ReturnCode_t::RETCODE_OK)
        {
            if (info.valid_data) describe(topic, m, ++received);
        }
    }
};

static void describe_pose(const std::string& topic, const gm::PoseWithCovarianceStamped_& m, int n)
{
    const auto& p = m.pose().pose().position();
    const auto& q = m.pose().pose().orientation();
    last_pose_stamp = stamp_of(m.header().stamp());
    char b[512];
    std::snprintf(b, sizeof b,
        "\"event\":\"pose\",\"topic\":\"%s\",\"n\":%d,\"stamp\":%.9f,\"frame\":\"%s\","
        "\"position\":[%.6f,%.6f,%.6f],\"orientation\":[%.6f,%.6f,%.6f,%.6f],"
        "\"cov_xx\":%.3g,\"wall\":%.6f",
        topic.c_str(), n, stamp_of(m.header().stamp()), esc(m.header().frame_id()).c_str(),
        p.x(), p.y(), p.z(), q.x(), q.y(), q.z(), q.w(), m.pose().covariance()[0], wall_s());
    emit(b);
}

static void describe_cloud(const std::string& topic, const sm::PointCloud2_& m, int n)
{
    std::string fields;
    for (const auto& f : m.fields())
    {
        fields += (fields.empty() ? "\"" : ",\"") + esc(f.name()) + "\"";
    }
    char b[512];
    std::snprintf(b, sizeof b,
        "\"event\":\"cloud\",\"topic\":\"%s\",\"n\":%d,\"stamp\":%.9f,\"frame\":\"%s\","
        "\"width\":%u,\"height\":%u,\"point_step\":%u,\"data_bytes\":%zu,\"fields\":[%s]",
        topic.c_str(), n, stamp_of(m.header().stamp()), esc(m.header().frame_id()).c_str(),
        m.width(), m.height(), m.point_step(), m.data().size(), fields.c_str());
    emit(b);
}

static void describe_diag(const std::string&, const dm::DiagnosticArray_& m, int)
{
    last_diag_stamp = stamp_of(m.header().stamp());
    for (const auto& s : m.status())
    {
        emit("\"event\":\"diag\",\"stamp\":" + std::to_string(stamp_of(m.header().stamp())) +
             ",\"level\":" + std::to_string(int(s.level())) + ",\"name\":\"" + esc(s.name()) +
             "\",\"message\":\"" + esc(s.message()) + "\"");
    }
}

static void describe_vector(const std::string& topic, const gm::Vector3Stamped_& m, int n)
{
    char b[512];
    std::snprintf(b, sizeof b,
        "\"event\":\"vector\",\"topic\":\"%s\",\"n\":%d,\"stamp\":%.9f,\"frame\":\"%s\","
        "\"vector\":[%.9g,%.9g,%.9g]",
        topic.c_str(), n, stamp_of(m.header().stamp()), esc(m.header().frame_id()).c_str(),
        m.vector().x(), m.vector().y(), m.vector().z());
    emit(b);
}

// ---------------------------------------------------------------------------------------
// Writer.

static std::atomic<int> writer_matches{0};

struct WriterEvents : public DataWriterListener
{
    std::string topic;

    void on_publication_matched(DataWriter*, const PublicationMatchedStatus& s) override
    {
        writer_matches = s.current_count;
        emit("\"event\":\"writer_matched\",\"topic\":\"" + topic + "\",\"current\":" +
             std::to_string(s.current_count) + ",\"change\":" + std::to_string(s.current_count_change));
    }

    void on_offered_incompatible_qos(DataWriter*, const OfferedIncompatibleQosStatus& s) override
    {
        emit("\"event\":\"writer_incompatible_qos\",\"topic\":\"" + topic + "\",\"policy\":" +
             std::to_string(s.last_policy_id) + ",\"total\":" + std::to_string(s.total_count));
    }
};

// x, y, z of a binary PCD file (the first three FLOAT32 fields), as 16-byte points.
static bool load_pcd(const std::string& path, std::vector<uint8_t>& out, uint32_t& n)
{
    std::ifstream f(path, std::ios::binary);
    if (!f) return false;
    std::string line;
    size_t point_size = 0;
    n = 0;
    while (std::getline(f, line))
    {
        std::istringstream ls(line);
        std::string key;
        ls >> key;
        if (key == "SIZE")
        {
            int s;
            while (ls >> s) point_size += s;
        }
        else if (key == "POINTS")
        {
            ls >> n;
        }
        else if (key == "DATA")
        {
            std::string kind;
            ls >> kind;
            if (kind != "binary") return false;
            break;
        }
    }
    std::vector<char> raw(static_cast<size_t>(n) * point_size);
    f.read(raw.data(), raw.size());
    if (static_cast<size_t>(f.gcount()) != raw.size() || point_size < 12) return false;
    out.assign(static_cast<size_t>(n) * 16, 0);
    for (uint32_t i = 0; i < n; ++i)
    {
        std::memcpy(&out[i * 16], &raw[i * point_size], 12);
    }
    return true;
}

static void synthetic_plane(std::vector<uint8_t>& out, uint32_t n, int k)
{
    // A tilted plane 1.5 m below the sensor, a square grid of n points, shifted by k cm.
    out.assign(static_cast<size_t>(n) * 16, 0);
    uint32_t side = static_cast<uint32_t>(std::ceil(std::sqrt(double(n))));
    for (uint32_t i = 0; i < n; ++i)
    {
        float xyz[3];
        xyz[0] = -10.0f + 20.0f * float(i % side) / float(side) + 0.01f * float(k);
        xyz[1] = -10.0f + 20.0f * float(i / side) / float(side);
        xyz[2] = -1.5f + 0.02f * xyz[0];
        std::memcpy(&out[i * 16], xyz, 12);
    }
}

static sm::PointField_ field(const char* name, uint32_t offset)
{
    sm::PointField_ f;
    f.name(name);
    f.offset(offset);
    f.datatype(7);  // FLOAT32
    f.count(1);
    return f;
}

// ---------------------------------------------------------------------------------------

// A reliable keep-last-1 writer on the ROS topic `name` (transient local: latched).
static DataWriter* reliable_writer(DomainParticipant* participant, Publisher* publisher,
    const std::string& name, TypeSupport& type, bool transient_local)
{
    Topic* t = participant->create_topic(ros_topic(name), type.get_type_name(), TOPIC_QOS_DEFAULT);
    if (!t) return nullptr;
    DataWriterQos q = publisher->get_default_datawriter_qos();
    q.reliability().kind = RELIABLE_RELIABILITY_QOS;
    q.durability().kind = transient_local ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
    q.history().kind = KEEP_LAST_HISTORY_QOS;
    q.history().depth = 1;
    return publisher->create_datawriter(t, q);
}

// `stamp` seconds as a ROS time.
static void set_stamp(builtin_interfaces::msg::dds_::Time_& time, double stamp)
{
    // The fraction rounded to nanoseconds, carried into the seconds when it rounds up
    // to a whole one (2.9999999999999996 is 3 s, not 2).
    double sec = std::floor(stamp);
    long long nanosec = std::llround((stamp - sec) * 1e9);
    if (nanosec >= 1000000000)
    {
        sec += 1.0;
        nanosec -= 1000000000;
    }
    time.sec(static_cast<int32_t>(sec));
    time.nanosec(static_cast<uint32_t>(nanosec));
}

// Waits up to `seconds` for `writer` to match a reader; whether it did.
static bool wait_for_reader(DataWriter* writer, double seconds)
{
    auto deadline = now_s() + seconds;
    PublicationMatchedStatus status;
    while (now_s() < deadline)
    {
        if (writer->get_publication_matched_status(status) == ReturnCode_t::RETCODE_OK && status.current_count > 0)
        {
            return true;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return false;
}

// The rows of whitespace-separated numbers in `path`, each of exactly `n`; false
// (naming the line on stderr) when the file is missing or a row is not.
static bool read_rows(const std::string& path, size_t n, std::vector<std::vector<double>>& rows)
{
    std::ifstream f(path);
    if (!f)
    {
        std::fprintf(stderr, "cannot read %s\n", path.c_str());
        return false;
    }
    std::string line;
    for (int number = 1; std::getline(f, line); ++number)
    {
        std::istringstream in(line);
        std::vector<double> row;
        double v;
        while (in >> v) row.push_back(v);
        if (row.empty()) continue;
        if (row.size() != n || !in.eof())
        {
            std::fprintf(stderr, "%s line %d: expected %zu numbers\n", path.c_str(), number, n);
            return false;
        }
        rows.push_back(std::move(row));
    }
    return true;
}

// The comma-separated numbers of `text` (exactly `n` of them), or an empty vector.
static std::vector<double> numbers(const std::string& text, size_t n)
{
    std::vector<double> v;
    std::stringstream in(text);
    std::string item;
    while (std::getline(in, item, ','))
    {
        try
        {
            v.push_back(std::stod(item));
        }
        catch (const std::exception&)
        {
            return {};
        }
    }
    if (v.size() != n) v.clear();
    return v;
}

// Latches `o.tf_static` ("parent,child,x,y,z,qx,qy,qz,qw") on /tf_static with ROS 2's
// static-transform QoS (reliable, transient local, keep-last 1), at once, without
// waiting for a reader; the writer stays up for the run. False when the value is
// malformed. Measured: a node that is already up when this is written during discovery
// may never see it (tools/fastdds/README.md); one that joins later does.
static bool publish_tf_static(DomainParticipant* participant, Publisher* publisher, const Options& o)
{
    auto first = o.tf_static.find(',');
    auto second = first == std::string::npos ? first : o.tf_static.find(',', first + 1);
    if (second == std::string::npos) return false;
    std::vector<double> v = numbers(o.tf_static.substr(second + 1), 7);
    if (v.empty()) return false;
    static TypeSupport tf_type(new tf2_msgs::msg::dds_::TFMessage_PubSubType());
    tf_type.register_type(participant);
    DataWriter* writer = reliable_writer(participant, publisher, "/tf_static", tf_type, true);
    if (!writer) return false;
    geometry_msgs::msg::dds_::TransformStamped_ link;
    link.header().frame_id(o.tf_static.substr(0, first));
    link.child_frame_id(o.tf_static.substr(first + 1, second - first - 1));
    auto& tr = link.transform();
    tr.translation().x(v[0]);
    tr.translation().y(v[1]);
    tr.translation().z(v[2]);
    tr.rotation().x(v[3]);
    tr.rotation().y(v[4]);
    tr.rotation().z(v[5]);
    tr.rotation().w(v[6]);
    tf2_msgs::msg::dds_::TFMessage_ m;
    m.transforms({link});
    bool ok = writer->write(&m);
    emit(std::string("\"event\":\"tf_static\",\"ok\":") + (ok ? "true" : "false"));
    return ok;
}

// Publishes `o.initial_pose` once on /initialpose (reliable, volatile, frame "map",
// stamped o.stamp0) once the node's reader matched; false when the value is malformed.
static bool publish_initial_pose(DomainParticipant* participant, Publisher* publisher,
    TypeSupport& pose_type, const Options& o)
{
    std::vector<double> v = numbers(o.initial_pose, 7);
    if (v.empty()) return false;
    DataWriter* writer = reliable_writer(participant, publisher, "/initialpose", pose_type, false);
    if (!writer) return false;
    bool matched = wait_for_reader(writer, o.wait_match);
    // Matched on this side only: the node's reader learns of this writer a moment
    // later, and a volatile sample written before that is not delivered (as DDS
    // allows); RViz's 2D Pose Estimate comes long after discovery.
    std::this_thread::sleep_for(std::chrono::milliseconds(1000));
    gm::PoseWithCovarianceStamped_ m;
    m.header().frame_id("map");
    double stamp = o.stamp0 >= 0 ? o.stamp0 : std::floor(wall_s());
    set_stamp(m.header().stamp(), stamp);
    auto& pose = m.pose().pose();
    pose.position().x(v[0]);
    pose.position().y(v[1]);
    pose.position().z(v[2]);
    pose.orientation().x(v[3]);
    pose.orientation().y(v[4]);
    pose.orientation().z(v[5]);
    pose.orientation().w(v[6]);
    bool ok = writer->write(&m);
    emit(std::string("\"event\":\"initial_pose\",\"matched\":") + (matched ? "true" : "false") +
         ",\"ok\":" + (ok ? "true" : "false"));
    // The node applies it to the next cloud: let it arrive first.
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    return ok;
}

// Set by SIGTERM / SIGINT: the waits end and the participant is deleted, so Fast DDS
// removes its shared-memory segments (a killed peer leaves them in /dev/shm).
static std::atomic<bool> stop_requested{false};

static void request_stop(int)
{
    stop_requested = true;
}

int main(int argc, char** argv)
{
    std::signal(SIGTERM, request_stop);
    std::signal(SIGINT, request_stop);
    Options o;
    if (!parse(argc, argv, o)) return 2;
    if (o.domain < 0)
    {
        const char* d = std::getenv("ROS_DOMAIN_ID");
        o.domain = d ? std::atoi(d) : 0;
    }

    auto* factory = DomainParticipantFactory::get_instance();
    // Fast DDS reads FASTRTPS_DEFAULT_PROFILES_FILE / DEFAULT_FASTRTPS_PROFILES.xml here:
    // a profile marked is_default_profile="true" becomes the default participant QoS.
    factory->load_profiles();
    DomainParticipantQos pqos = factory->get_default_participant_qos();
    pqos.name("fdpeer");
    if (o.no_shm)
    {
        pqos.transport().use_builtin_transports = false;
        auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
        if (o.socket_buffer > 0)
        {
            udp->sendBufferSize = o.socket_buffer;
            udp->receiveBufferSize = o.socket_buffer;
        }
        pqos.transport().user_transports.push_back(udp);
    }
    if (o.socket_buffer > 0)
    {
        pqos.transport().send_socket_buffer_size = o.socket_buffer;
        pqos.transport().listen_socket_buffer_size = o.socket_buffer;
    }
    ParticipantListener plistener;
    plistener.log = o.discovery_log;
    DomainParticipant* participant =
        factory->create_participant(o.domain, pqos, &plistener, StatusMask::none());
    if (!participant)
    {
        std::fprintf(stderr, "could not create the participant\n");
        return 1;
    }
    emit("\"event\":\"start\",\"domain\":" + std::to_string(o.domain) + ",\"no_shm_flag\":" +
         (o.no_shm ? "true" : "false") + ",\"builtin_transports\":" +
         (participant->get_qos().transport().use_builtin_transports ? "true" : "false") +
         ",\"user_transports\":" + std::to_string(participant->get_qos().transport().user_transports.size()));

    TypeSupport cloud_type(new sm::PointCloud2_PubSubType());
    TypeSupport pose_type(new gm::PoseWithCovarianceStamped_PubSubType());
    TypeSupport diag_type(new dm::DiagnosticArray_PubSubType());
    TypeSupport vector_type(new gm::Vector3Stamped_PubSubType());
    cloud_type.register_type(participant);
    pose_type.register_type(participant);
    diag_type.register_type(participant);
    vector_type.register_type(participant);

    Publisher* publisher = participant->create_publisher(PUBLISHER_QOS_DEFAULT);
    Subscriber* subscriber = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT);

    auto reader_qos = [&](bool transient_local, int depth) {
        DataReaderQos q = subscriber->get_default_datareader_qos();
        if (o.qos_from_xml) return q;
        q.reliability().kind = o.best_effort_sub ? BEST_EFFORT_RELIABILITY_QOS : RELIABLE_RELIABILITY_QOS;
        q.durability().kind = transient_local ? TRANSIENT_LOCAL_DURABILITY_QOS : VOLATILE_DURABILITY_QOS;
        q.history().kind = KEEP_LAST_HISTORY_QOS;
        q.history().depth = depth;
        return q;
    };

    // Latched first, as robot_state_publisher does at start-up: a reader that joins
    // later gets it from the writer's history (transient local).
    if (!o.tf_static.empty() && !publish_tf_static(participant, publisher, o))
    {
        std::fprintf(stderr, "--tf-static: expected PARENT,CHILD,X,Y,Z,QX,QY,QZ,QW\n");
        return 1;
    }
    // Each subscription: its listener, on the ROS topic `name`, reliable unless
    // --best-effort-sub.
    auto subscribe = [&](ReaderEvents& listener, const std::string& name, TypeSupport& type,
                         bool transient_local, int depth) {
        listener.topic = ros_topic(name);
        Topic* t = participant->create_topic(listener.topic, type.get_type_name(), TOPIC_QOS_DEFAULT);
        return t && subscriber->create_datareader(t, reader_qos(transient_local, depth), &listener);
    };
    Reader<gm::PoseWithCovarianceStamped_> pose_listener(poses_received, describe_pose);
    Reader<sm::PointCloud2_> cloud_listener(clouds_received, describe_cloud);
    Reader<dm::DiagnosticArray_> diag_listener(diags_received, describe_diag);
    Reader<gm::Vector3Stamped_> vector_listener(vectors_received, describe_vector);
    if (!o.sub_pose.empty() && !subscribe(pose_listener, o.sub_pose, pose_type, false, 10)) return 1;
    if (!o.sub_cloud.empty() && !subscribe(cloud_listener, o.sub_cloud, cloud_type, o.cloud_transient_local, 1))
        return 1;
    if (o.lockstep > 0 && o.sub_diag.empty())
    {
        std::fprintf(stderr, "--lockstep needs --sub-diag (the node's diagnostics say a cloud was taken)\n");
        return 1;
    }
    if (!o.sub_diag.empty() && !subscribe(diag_listener, o.sub_diag, diag_type, false, 10)) return 1;
    // Latched, as the node publishes the map frame's gravity.
    if (!o.sub_vector.empty() && !subscribe(vector_listener, o.sub_vector, vector_type, true, 1)) return 1;

    int sent = 0, send_failed = 0;
    double last_sent_stamp = -1.0;
    auto done_expecting = [&]() {
        bool poses_done = o.expect_poses >= 0 && poses_received >= o.expect_poses;
        bool clouds_done = o.expect_clouds >= 0 && clouds_received >= o.expect_clouds;
        bool last_done = o.until_last_pose && sent > 0 && same_stamp(last_pose_stamp, last_sent_stamp);
        return poses_done || clouds_done || last_done;
    };

    if (!o.pub_points.empty())
    {
        WriterEvents wlistener;
        wlistener.topic = ros_topic(o.pub_points);
        Topic* t = participant->create_topic(wlistener.topic, cloud_type.get_type_name(), TOPIC_QOS_DEFAULT);
        // Sensor data as a driver publishes it: best effort (reliable with --reliable),
        // volatile, keep-last `depth`; the XML profile's QoS with --qos-from-xml.
        auto sensor_qos = [&](int depth) {
            DataWriterQos q = publisher->get_default_datawriter_qos();
            if (o.qos_from_xml) return q;
            q.reliability().kind = o.reliable ? RELIABLE_RELIABILITY_QOS : BEST_EFFORT_RELIABILITY_QOS;
            q.durability().kind = VOLATILE_DURABILITY_QOS;
            q.history().kind = KEEP_LAST_HISTORY_QOS;
            q.history().depth = depth;
            if (o.async) q.publish_mode().kind = ASYNCHRONOUS_PUBLISH_MODE;
            return q;
        };
        DataWriter* writer = publisher->create_datawriter(t, sensor_qos(o.depth), &wlistener);
        if (!writer) return 1;
        auto q = writer->get_qos();
        emit("\"event\":\"writer\",\"topic\":\"" + wlistener.topic + "\",\"type\":\"" +
             cloud_type.get_type_name() + "\",\"reliable\":" +
             (q.reliability().kind == RELIABLE_RELIABILITY_QOS ? "true" : "false") + ",\"depth\":" +
             std::to_string(q.history().depth) + ",\"async\":" +
             (q.publish_mode().kind == ASYNCHRONOUS_PUBLISH_MODE ? "true" : "false") +
             ",\"memory_policy\":" + std::to_string(int(q.endpoint().history_memory_policy)));

        // The IMU: its history holds a cloud's worth of samples written back to back.
        std::vector<std::vector<double>> imu;
        DataWriter* imu_writer = nullptr;
        TypeSupport imu_type(new sm::Imu_PubSubType());
        if (!o.pub_imu.empty())
        {
            if (o.imu_file.empty() || !read_rows(o.imu_file, 7, imu)) return 1;
            imu_type.register_type(participant);
            Topic* it = participant->create_topic(ros_topic(o.pub_imu), imu_type.get_type_name(), TOPIC_QOS_DEFAULT);
            imu_writer = it ? publisher->create_datawriter(it, sensor_qos(1000)) : nullptr;
            if (!imu_writer) return 1;
        }
        auto deadline = now_s() + o.wait_match;
        while (writer_matches == 0 && now_s() < deadline)
        {
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        if (writer_matches == 0) emit("\"event\":\"no_match\",\"topic\":\"" + wlistener.topic + "\"");
        if (imu_writer && !wait_for_reader(imu_writer, std::max(0.0, deadline - now_s())))
        {
            emit("\"event\":\"no_match\",\"topic\":\"" + ros_topic(o.pub_imu) + "\"");
        }
        // Give the remote reader a moment past the match (its side of discovery). A
        // best-effort reader drops a sample from a writer it has not yet discovered, and
        // Fast DDS repairs a lost discovery message on its 3 s heartbeat: the tests want
        // every cloud to arrive, so past one heartbeat (a loaded clean-clone CI run lost
        // the first cloud after 0.5 s).
        std::this_thread::sleep_for(std::chrono::milliseconds(3500));
        if (!o.initial_pose.empty() && !publish_initial_pose(participant, publisher, pose_type, o))
        {
            std::fprintf(stderr, "--initial-pose: expected X,Y,Z,QX,QY,QZ,QW\n");
            return 1;
        }

        sm::PointCloud2_ cloud;
        cloud.header().frame_id(o.frame);
        cloud.height(1);
        cloud.fields({field("x", 0), field("y", 4), field("z", 8)});
        cloud.is_bigendian(false);
        cloud.point_step(o.point_step);
        cloud.is_dense(true);
        std::vector<std::vector<uint8_t>> scans;
        if (!o.pcd_dir.empty())
        {
            for (int k = 0; o.pcd_count == 0 || k < o.pcd_count; ++k)
            {
                char p[64];
                std::snprintf(p, sizeof p, "/%06d.pcd", o.pcd_first + k);
                std::vector<uint8_t> d;
                uint32_t n;
                if (!load_pcd(o.pcd_dir + p, d, n)) break;
                scans.push_back(std::move(d));
            }
            if (scans.empty())
            {
                std::fprintf(stderr, "no PCD scans in %s\n", o.pcd_dir.c_str());
                return 1;
            }
        }
        std::vector<std::vector<double>> stamps;
        if (!o.stamps_file.empty() && !read_rows(o.stamps_file, 1, stamps)) return 1;
        if (!o.stamps_file.empty() && stamps.size() < size_t(o.count))
        {
            std::fprintf(stderr, "--stamps-file has %zu stamps for %d clouds\n", stamps.size(), o.count);
            return 1;
        }
        size_t imu_next = 0;
        int imu_sent = 0;
        sm::Imu_ sample;
        sample.header().frame_id("imu");
        sample.orientation().w(1.0);
        sample.orientation_covariance()[0] = -1.0;  // no orientation (REP 145)
        double stamp0 = o.stamp0 >= 0 ? o.stamp0 : std::floor(wall_s());
        auto period = std::chrono::duration<double>(1.0 / o.rate);
        auto next = std::chrono::steady_clock::now();
        for (int k = 0; k < o.count; ++k)
        {
            std::vector<uint8_t> data;
            if (scans.empty()) synthetic_plane(data, o.points, k);
            else data = scans[k % scans.size()];
            uint32_t n = static_cast<uint32_t>(data.size() / 16);
            if (o.point_step != 16)
            {
                std::vector<uint8_t> wide(static_cast<size_t>(n) * o.point_step, 0);
                for (uint32_t i = 0; i < n; ++i) std::memcpy(&wide[size_t(i) * o.point_step], &data[size_t(i) * 16], 12);
                data.swap(wide);
            }
            double stamp = !stamps.empty() ? stamps[k][0]
                                           : stamp0 + k * (o.stamp_step > 0 ? o.stamp_step : 1.0 / o.rate);
            bool wrote_imu = false;
            for (; imu_writer && imu_next < imu.size() && imu[imu_next][0] <= stamp + o.imu_ahead; ++imu_next)
            {
                const auto& r = imu[imu_next];
                set_stamp(sample.header().stamp(), r[0]);
                sample.linear_acceleration().x(r[1]);
                sample.linear_acceleration().y(r[2]);
                sample.linear_acceleration().z(r[3]);
                sample.angular_velocity().x(r[4]);
                sample.angular_velocity().y(r[5]);
                sample.angular_velocity().z(r[6]);
                imu_sent += imu_writer->write(&sample) ? 1 : 0;
                wrote_imu = true;
            }
            // A driver's samples up to the stamp went out while the sweep lasted: a
            // moment for them to arrive before the cloud (readers of two topics are
            // not ordered with each other).
            if (wrote_imu) std::this_thread::sleep_for(std::chrono::milliseconds(20));
            set_stamp(cloud.header().stamp(), stamp);
            cloud.width(n);
            cloud.row_step(n * o.point_step);
            cloud.data(std::move(data));
            double before = now_s();
            bool ok = writer->write(&cloud);
            double took = now_s() - before;
            if (ok)
            {
                ++sent;
                last_sent_stamp = stamp;
            }
            else ++send_failed;
            char b[256];
            std::snprintf(b, sizeof b,
                "\"event\":\"sent\",\"topic\":\"%s\",\"k\":%d,\"ok\":%s,\"stamp\":%.9f,\"points\":%u,"
                "\"data_bytes\":%u,\"write_ms\":%.3f,\"wall\":%.6f",
                wlistener.topic.c_str(), k, ok ? "true" : "false", stamp, n, n * o.point_step, took * 1e3, wall_s());
            emit(b);
            if (ok && o.lockstep > 0)
            {
                auto give_up = now_s() + o.lockstep;
                while (!same_stamp(last_diag_stamp, stamp) && now_s() < give_up && !stop_requested)
                    std::this_thread::sleep_for(std::chrono::milliseconds(2));
                if (!same_stamp(last_diag_stamp, stamp))
                    emit("\"event\":\"lockstep_timeout\",\"k\":" + std::to_string(k));
            }
            next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
            std::this_thread::sleep_until(next);
        }
        auto end = now_s() + o.linger;
        while (now_s() < end && !done_expecting() && !stop_requested)
        {
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        emit("\"event\":\"summary\",\"sent\":" + std::to_string(sent) + ",\"send_failed\":" +
             std::to_string(send_failed) + ",\"poses\":" + std::to_string(poses_received.load()) +
             ",\"clouds\":" + std::to_string(clouds_received.load()) + ",\"diags\":" +
             std::to_string(diags_received.load()) + ",\"imu_sent\":" + std::to_string(imu_sent));
        publisher->delete_datawriter(writer);
        if (imu_writer) publisher->delete_datawriter(imu_writer);
    }
    else
    {
        auto end = now_s() + (o.duration > 0 ? o.duration : o.linger);
        while (now_s() < end && !done_expecting() && !stop_requested)
        {
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
        emit("\"event\":\"summary\",\"sent\":0,\"poses\":" + std::to_string(poses_received.load()) +
             ",\"clouds\":" + std::to_string(clouds_received.load()) + ",\"diags\":" +
             std::to_string(diags_received.load()));
    }
    participant->delete_contained_entities();
    factory->delete_participant(participant);
    return 0;
}
