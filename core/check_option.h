// The one check of an Options struct's fields, after COLMAP's CHECK_OPTION_GT and Ceres'
// OPTION_GE: used inside `Options::Check() const`, each macro throws an OptionError whose
// message names the struct, the field, its value and the bound it violates:
//
//   HOLOCAP_CHECK_OPTION_GE(kl_weight, 0);
//     NeuralVolumeOptions::kl_weight = -1 violates kl_weight >= 0
//   HOLOCAP_CHECK_OPTION_IN(max_hamming, 0, 3);
//     DetectionOptions::max_hamming = 5 violates max_hamming in [0, 3]
//   HOLOCAP_CHECK_OPTION_GT(depth_max_m, depth_min_m);
//     ScanOptions::depth_max_m = 0.2 violates depth_max_m > depth_min_m (0.3)
//   HOLOCAP_CHECK_OPTION(IsPowerOfTwo(grid), grid);
//     NeuralVolumeOptions::grid = 48 violates IsPowerOfTwo(grid)
//
// Every macro takes an optional last argument, an explanation (a string, built only on failure)
// printed after the bound: HOLOCAP_CHECK_OPTION_GE(threads, 0, "0: all cores") ends
// "violates threads >= 0 (0: all cores)". A bound that is not a number is printed with its value.
// The comparisons are written so that NaN fails every one of them. HOLOCAP_CHECK_OPTION takes a
// condition the caller writes to be true for valid values (NaN included: `x > 0 && x < 1`, not
// `!(x <= 0)`), and the field it names: the principal one where a check spans several.
//
// The CLI (app/main.cpp) catches OptionError and names the flag the user typed in place of the
// field: "--kl-weight -1 violates kl_weight >= 0".
#pragma once

#include <charconv>
#include <filesystem>
#include <initializer_list>
#include <optional>
#include <ranges>
#include <string>
#include <string_view>
#include <type_traits>

#include "core/error.h"

namespace holocap {

class OptionError : public Error {
 public:
  // `options`: the struct ("NeuralVolumeOptions"; empty where not known); `field` as written in
  // the check ("kl_weight", "render.step_voxels"); `value` as printed (empty where the type has
  // no printed form); `constraint` the violated bound ("kl_weight >= 0").
  OptionError(std::string options, std::string field, std::string value, std::string constraint,
              std::string explanation);

  const std::string& options() const { return options_; }
  const std::string& field() const { return field_; }
  const std::string& value() const { return value_; }
  const std::string& constraint() const { return constraint_; }
  const std::string& explanation() const { return explanation_; }

  // The message with `name` (a flag and the text typed after it: "--kl-weight -1") in place of
  // "NeuralVolumeOptions::kl_weight = -1".
  std::string NamedAs(const std::string& name) const;

 private:
  std::string options_, field_, value_, constraint_, explanation_;
};

// Whether `value` is one of `allowed`: HOLOCAP_CHECK_OPTION(IsOneOf(scene, {"auto", "static"}),
// scene) prints the allowed values in its condition.
template <typename T, typename U>
bool IsOneOf(const T& value, std::initializer_list<U> allowed) {
  for (const U& candidate : allowed)
    if (value == candidate) return true;
  return false;
}

namespace check_option_internal {

// How a value reads in a message: numbers in their shortest exact form, strings and paths
// quoted, enums by their ToString, ranges as [a, b, ...]; nullopt for a type without a printed
// form. Long texts are cut.
template <typename T>
std::optional<std::string> ValueText(const T& value) {
  if constexpr (std::is_same_v<T, bool>) {
    return value ? "true" : "false";
  } else if constexpr (std::is_floating_point_v<T>) {
    char text[64];
    const auto end = std::to_chars(text, text + sizeof(text), value).ptr;
    return std::string(text, end);
  } else if constexpr (std::is_integral_v<T>) {
    return std::to_string(value);
  } else if constexpr (std::is_convertible_v<const T&, std::string_view>) {
    return Cat("'", std::string_view(value), "'");
  } else if constexpr (std::is_same_v<T, std::filesystem::path>) {
    return Cat("'", value.string(), "'");
  } else if constexpr (requires { std::string(ToString(value)); }) {
    return std::string(ToString(value));
  } else if constexpr (requires { std::string(value.ToString()); }) {
    return std::string(value.ToString());
  } else if constexpr (requires { std::string(value.dump()); }) {
    return std::string(value.dump());
  } else if constexpr (requires {
                         value.has_value();
                         *value;
                       }) {
    if (!value.has_value()) return "none";
    return ValueText(*value);
  } else if constexpr (std::ranges::range<const T>) {
    std::string text = "[";
    for (const auto& element : value) {
      const auto element_text = ValueText(element);
      if (!element_text) return std::nullopt;
      text += (text.size() > 1 ? ", " : "") + *element_text;
    }
    return text + "]";
  } else {
    return std::nullopt;
  }
}

// The struct whose Check() `function` (__PRETTY_FUNCTION__) is: "NeuralVolumeOptions" for
// "void holocap::NeuralVolumeOptions::Check() const"; empty for any other function.
std::string OptionsOf(std::string_view function);

// `text` where it is a number as written, else "text (value)".
std::string BoundText(std::string_view text, const std::optional<std::string>& value);

[[noreturn]] void Throw(std::string_view function, std::string_view field,
                        const std::optional<std::string>& value, std::string constraint,
                        std::string_view explanation = {});

template <typename T, typename B>
[[noreturn]] void FailRelation(std::string_view function, std::string_view field, const T& value,
                               std::string_view relation, std::string_view bound_text,
                               const B& bound, std::string_view explanation = {}) {
  Throw(function, field, ValueText(value),
        Cat(field, " ", relation, " ", BoundText(bound_text, ValueText(bound))), explanation);
}

template <typename T, typename L, typename H>
[[noreturn]] void FailRange(std::string_view function, std::string_view field, const T& value,
                            std::string_view lo_text, const L& lo, std::string_view hi_text,
                            const H& hi, std::string_view explanation = {}) {
  Throw(function, field, ValueText(value),
        Cat(field, " in [", BoundText(lo_text, ValueText(lo)), ", ",
            BoundText(hi_text, ValueText(hi)), "]"),
        explanation);
}

template <typename T>
[[noreturn]] void FailCondition(std::string_view function, std::string_view field, const T& value,
                                std::string_view condition, std::string_view explanation = {}) {
  Throw(function, field, ValueText(value), std::string(condition), explanation);
}

}  // namespace check_option_internal
}  // namespace holocap

#define HOLOCAP_CHECK_OPTION_RELATION_(field, relation, bound, ...)                      \
  do {                                                                                   \
    if (!((field)relation(bound))) {                                                     \
      ::holocap::check_option_internal::FailRelation(__PRETTY_FUNCTION__, #field, field, \
                                                     #relation, #bound,                  \
                                                     bound __VA_OPT__(, ) __VA_ARGS__);  \
    }                                                                                    \
  } while (false)

// field > bound, field >= bound, field < bound, field <= bound, field == bound.
#define HOLOCAP_CHECK_OPTION_GT(field, bound, ...) \
  HOLOCAP_CHECK_OPTION_RELATION_(field, >, bound, __VA_ARGS__)
#define HOLOCAP_CHECK_OPTION_GE(field, bound, ...) \
  HOLOCAP_CHECK_OPTION_RELATION_(field, >=, bound, __VA_ARGS__)
#define HOLOCAP_CHECK_OPTION_LT(field, bound, ...) \
  HOLOCAP_CHECK_OPTION_RELATION_(field, <, bound, __VA_ARGS__)
#define HOLOCAP_CHECK_OPTION_LE(field, bound, ...) \
  HOLOCAP_CHECK_OPTION_RELATION_(field, <=, bound, __VA_ARGS__)
#define HOLOCAP_CHECK_OPTION_EQ(field, bound, ...) \
  HOLOCAP_CHECK_OPTION_RELATION_(field, ==, bound, __VA_ARGS__)

// lo <= field <= hi (a closed range; an open end is a _GT or _LT of its own).
#define HOLOCAP_CHECK_OPTION_IN(field, lo, hi, ...)                                            \
  do {                                                                                         \
    if (!((field) >= (lo) && (field) <= (hi))) {                                               \
      ::holocap::check_option_internal::FailRange(__PRETTY_FUNCTION__, #field, field, #lo, lo, \
                                                  #hi, hi __VA_OPT__(, ) __VA_ARGS__);         \
    }                                                                                          \
  } while (false)

// Anything else: `condition` holds for a valid `field`.
#define HOLOCAP_CHECK_OPTION(condition, field, ...)                                           \
  do {                                                                                        \
    if (!(condition)) {                                                                       \
      ::holocap::check_option_internal::FailCondition(__PRETTY_FUNCTION__, #field, field,     \
                                                      #condition __VA_OPT__(, ) __VA_ARGS__); \
    }                                                                                         \
  } while (false)
