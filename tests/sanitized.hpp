#pragma once
// Whether this test binary was built with AddressSanitizer: ASan reserves terabytes of shadow
// address space (so address-space caps cannot apply) and runs several times slower (so time
// budgets are skipped, not widened).
namespace cf::test {
#if defined(__SANITIZE_ADDRESS__)
inline constexpr bool kSanitized = true;
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
inline constexpr bool kSanitized = true;
#else
inline constexpr bool kSanitized = false;
#endif
#else
inline constexpr bool kSanitized = false;
#endif
}  // namespace cf::test
