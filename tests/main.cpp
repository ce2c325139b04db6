// The doctest runner shared by every test program. A run whose filters match no test case fails:
// with EPONA_TEST_UNITY, ctest runs each file of a folder's program through a --source-file filter
// (tests/CMakeLists.txt), and a filter that matched nothing would otherwise pass having run nothing.
#define DOCTEST_CONFIG_IMPLEMENT
#include <doctest/doctest.h>

#include <cstdio>

namespace {

int matched_test_cases = -1;  // set at the end of a run; queries (--help, --list-*) leave it at -1

// A listener only for the run's totals; every other event is ignored.
struct MatchedTestCases : doctest::IReporter {
  explicit MatchedTestCases(const doctest::ContextOptions&) {}
  void report_query(const doctest::QueryData&) override {}
  void test_run_start() override {}
  void test_run_end(const doctest::TestRunStats& stats) override {
    matched_test_cases = static_cast<int>(stats.numTestCasesPassingFilters);
  }
  void test_case_start(const doctest::TestCaseData&) override {}
  void test_case_reenter(const doctest::TestCaseData&) override {}
  void test_case_end(const doctest::CurrentTestCaseStats&) override {}
  void test_case_exception(const doctest::TestCaseException&) override {}
  void subcase_start(const doctest::SubcaseSignature&) override {}
  void subcase_end() override {}
  void log_assert(const doctest::AssertData&) override {}
  void log_message(const doctest::MessageData&) override {}
  void test_case_skipped(const doctest::TestCaseData&) override {}
};

}  // namespace

DOCTEST_REGISTER_LISTENER("matched_test_cases", 1, MatchedTestCases);

int main(int argc, char** argv) {
  doctest::Context context(argc, argv);
  const int result = context.run();
  if (context.shouldExit() || matched_test_cases != 0) return result;
  std::fprintf(stderr, "no test case matches this run's filters: nothing was tested\n");
  return 1;
}
