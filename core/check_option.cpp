#include "core/check_option.h"

#include <cctype>
#include <cstdlib>
#include <utility>

namespace holocap {
namespace {

// A value longer than this (a list, a JSON object) is cut: the message stays one short line.
constexpr size_t kMaxValueText = 80;

std::string WithExplanation(std::string text, const std::string& explanation) {
  if (!explanation.empty()) text += " (" + explanation + ")";
  return text;
}

std::string Message(const std::string& options, const std::string& field, const std::string& value,
                    const std::string& constraint, const std::string& explanation) {
  std::string name = options.empty() ? field : options + "::" + field;
  if (!value.empty()) name += " = " + value;
  return WithExplanation(name + " violates " + constraint, explanation);
}

bool IsIdentifierChar(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '_';
}

}  // namespace

OptionError::OptionError(std::string options, std::string field, std::string value,
                         std::string constraint, std::string explanation)
    : Error(Message(options, field, value, constraint, explanation)),
      options_(std::move(options)),
      field_(std::move(field)),
      value_(std::move(value)),
      constraint_(std::move(constraint)),
      explanation_(std::move(explanation)) {}

std::string OptionError::NamedAs(const std::string& name) const {
  return WithExplanation(name + " violates " + constraint_, explanation_);
}

namespace check_option_internal {

std::string OptionsOf(std::string_view function) {
  const size_t check = function.find("::Check(");
  if (check == std::string_view::npos) return "";
  size_t begin = check;
  while (begin > 0 && IsIdentifierChar(function[begin - 1])) --begin;
  return std::string(function.substr(begin, check - begin));
}

std::string BoundText(std::string_view text, const std::optional<std::string>& value) {
  const std::string bound(text);
  const bool starts_like_number =
      !bound.empty() && (std::isdigit(static_cast<unsigned char>(bound[0])) != 0 ||
                         bound[0] == '-' || bound[0] == '+' || bound[0] == '.');
  char* end = nullptr;
  std::strtod(bound.c_str(), &end);
  if (starts_like_number && end == bound.c_str() + bound.size()) return bound;
  if (!value || *value == bound) return bound;
  return bound + " (" + *value + ")";
}

void Throw(std::string_view function, std::string_view field,
           const std::optional<std::string>& value, std::string constraint,
           std::string_view explanation) {
  std::string value_text = value.value_or("");
  if (value_text.size() > kMaxValueText) value_text = value_text.substr(0, kMaxValueText) + "...";
  throw OptionError(OptionsOf(function), std::string(field), std::move(value_text),
                    std::move(constraint), std::string(explanation));
}

}  // namespace check_option_internal
}  // namespace holocap
