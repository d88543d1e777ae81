// Decodes event_camera_msgs/EventPacket payloads with event_camera_codecs' own decoders (unmodified,
// from a checkout given at build time), as a ROS node would: one decoder per topic from the
// DecoderFactory, fed message after message.
//
// stdin, per packet:  u8 topic id, u8 encoding length, encoding, u32 width, u32 height,
//                     u64 time_base, u32 payload bytes, payload
// stdout, per event:  u8 topic id, u8 kind (0: CD event, 1: trigger edge), u64 sensor time (ns),
//                     u16 x (edge: its id), u16 y, u8 polarity (edge: its level)
#include <event_camera_codecs/decoder_factory.h>
#include <event_camera_codecs/event_processor.h>

#include <cstdio>
#include <map>
#include <string>
#include <vector>

using event_camera_codecs::EventPacket;

namespace
{
#pragma pack(push, 1)
struct Row
{
  uint8_t topic;
  uint8_t kind;
  uint64_t t;
  uint16_t x;
  uint16_t y;
  uint8_t p;
};
#pragma pack(pop)

class Writer : public event_camera_codecs::EventProcessor
{
public:
  uint8_t topic{0};
  std::vector<Row> rows;
  void eventCD(uint64_t t, uint16_t x, uint16_t y, uint8_t p) override { rows.push_back({topic, 0, t, x, y, p}); }
  void eventExtTrigger(uint64_t t, uint8_t edge, uint8_t id) override { rows.push_back({topic, 1, t, id, 0, edge}); }
  void finished() override {}
  void rawData(const char *, size_t) override {}
};

bool readAll(void * dst, size_t n) { return n == 0 || std::fread(dst, 1, n, stdin) == n; }
}  // namespace

int main()
{
  std::map<uint8_t, event_camera_codecs::DecoderFactory<EventPacket, Writer>> factories;
  Writer out;
  while (true) {
    uint8_t topic = 0, encLen = 0;
    if (!readAll(&topic, 1)) break;
    EventPacket msg;
    std::string enc(255, '\0');
    uint32_t n = 0;
    if (!readAll(&encLen, 1) || !readAll(enc.data(), encLen) || !readAll(&msg.width, 4) ||
        !readAll(&msg.height, 4) || !readAll(&msg.time_base, 8) || !readAll(&n, 4)) {
      std::fprintf(stderr, "truncated packet header\n");
      return 2;
    }
    enc.resize(encLen);
    msg.encoding = enc;
    msg.events.resize(n);
    if (!readAll(msg.events.data(), n)) {
      std::fprintf(stderr, "truncated packet payload\n");
      return 2;
    }
    auto * decoder = factories[topic].getInstance(msg);
    if (decoder == nullptr) {
      std::fprintf(stderr, "no decoder for encoding %s\n", enc.c_str());
      return 3;
    }
    out.topic = topic;
    decoder->decode(msg, &out);
    std::fwrite(out.rows.data(), sizeof(Row), out.rows.size(), stdout);
    out.rows.clear();
  }
  return 0;
}
