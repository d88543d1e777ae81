// The fields of event_camera_msgs/msg/EventPacket that event_camera_codecs reads, standing in for
// the header a ROS 2 build generates from the .msg (rigd/products/ros/msg/event_camera_msgs/).
#ifndef RIGD_CHECK_EVENT_PACKET_HPP_
#define RIGD_CHECK_EVENT_PACKET_HPP_
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

namespace event_camera_msgs::msg
{
struct EventPacket
{
  uint32_t height{0};
  uint32_t width{0};
  uint32_t seq{0};
  uint64_t time_base{0};
  std::string encoding;
  bool is_bigendian{false};
  std::vector<uint8_t> events;
  using ConstSharedPtr = std::shared_ptr<const EventPacket>;
};
}  // namespace event_camera_msgs::msg
#endif
