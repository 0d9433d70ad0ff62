#pragma once
// Frame conversion of the V4L2 backend, apart from the device so it is testable without one.
#include <cstddef>
#include <cstdint>
#include <opencv2/core.hpp>
#include <string>

namespace cf::camera::detail {

/// "MJPG" -> the fourcc code, and back.
uint32_t fourcc_code(const std::string& s);
std::string fourcc_string(uint32_t code);

/// One captured buffer to 8-bit BGR. MJPG: JPEG decode (libjpeg-turbo supplies the standard
/// Huffman tables webcams leave out); YUYV: 4:2:2 to BGR; BGR3/RGB3 (what libv4l2 converts
/// other formats to): copy. Returns an empty Mat for a truncated or undecodable buffer.
cv::Mat convert_frame(const std::string& fourcc, const uint8_t* data, size_t bytes, int width, int height, int bytes_per_line);

}  // namespace cf::camera::detail
