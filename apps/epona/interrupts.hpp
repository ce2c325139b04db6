// apps/epona/interrupts.hpp — what the program does on SIGINT, SIGTERM and SIGHUP: removes the
// temporary files of the writes in progress (io::remove_temporary_files), says so, and dies of
// the signal as it would have (exit status 128 + N for the shell). Output folders of long runs
// carry an INCOMPLETE note until they finish (output_paths.hpp), which needs no handler at all.
#pragma once

#include <signal.h>
#include <unistd.h>

#include "epona/io/atomic_file.hpp"

namespace epona::app {

namespace interrupt_detail {
inline void on_signal(int sig) {
  io::remove_temporary_files();
  static const char msg[] = "\nepona: interrupted; removed the partial output files\n";
  (void)!::write(STDERR_FILENO, msg, sizeof msg - 1);
  ::signal(sig, SIG_DFL);
  ::raise(sig);
}
}  // namespace interrupt_detail

inline void install_interrupt_handlers() {
  struct sigaction sa {};
  sa.sa_handler = interrupt_detail::on_signal;
  sigemptyset(&sa.sa_mask);
  for (int sig : {SIGINT, SIGTERM, SIGHUP}) ::sigaction(sig, &sa, nullptr);
}

}  // namespace epona::app
